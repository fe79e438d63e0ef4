//! The build-time check of the GPU backend's WGSL (build.rs; also
//! tests/wgsl_build.rs, which feeds it broken copies): every module
//! src/render/gpu/wgsl.rs assembles is parsed and validated by naga, the
//! shader compiler wgpu itself uses, with its override constants left
//! overridable (each has a default in the source).

use naga::valid::{Capabilities, ValidationFlags, Validator};

/// Parses and validates one assembled module; `Err` is naga's report
/// (the offending lines, with the module's name).
pub fn validate(name: &str, source: &str) -> Result<(), String> {
    let module = naga::front::wgsl::parse_str(source)
        .map_err(|e| e.emit_to_string_with_path(source, name))?;
    Validator::new(ValidationFlags::all(), Capabilities::default())
        .validate(&module)
        .map_err(|e| e.emit_to_string_with_path(source, name))?;
    Ok(())
}

/// Validates every named module; `Err` joins the reports of all that fail.
pub fn validate_all(modules: &[(String, String)]) -> Result<(), String> {
    let errors: Vec<String> = modules
        .iter()
        .filter_map(|(name, source)| validate(name, source).err())
        .collect();
    if errors.is_empty() {
        Ok(())
    } else {
        Err(errors.join("\n"))
    }
}
