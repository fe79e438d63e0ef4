//! With the `gpu` feature: a syntax or type error in any .wgsl file of
//! src/render/gpu fails the build, instead of the first render at run time.

#[cfg(feature = "gpu")]
#[path = "build/validate.rs"]
mod validate;
#[cfg(feature = "gpu")]
#[path = "src/render/gpu/wgsl.rs"]
#[allow(dead_code)] // the runtime's half of the module
mod wgsl;

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=build/validate.rs");
    println!("cargo:rerun-if-changed=src/render/gpu");
    #[cfg(feature = "gpu")]
    if let Err(report) = validate::validate_all(&wgsl::all_modules(wgsl::FILES)) {
        eprintln!("{report}");
        println!("cargo:warning=invalid WGSL in src/render/gpu (report above)");
        std::process::exit(1);
    }
}
