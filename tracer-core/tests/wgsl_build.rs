//! The build-time WGSL check (build.rs): the same function build.rs runs,
//! on the modules as the backend assembles them, then on copies with one
//! file broken, which must be refused with naga's report naming the file,
//! line and module. (By hand: append `fn broken() { let x = ; }` to any .wgsl file
//! in src/render/gpu and `cargo build -p tracer-core` fails with that report.)

#[path = "../build/validate.rs"]
mod validate;
#[path = "../src/render/gpu/wgsl.rs"]
#[allow(dead_code)]
mod wgsl;

/// Every module with `name`'s text replaced by `text`.
fn modules_with(name: &str, text: &str) -> Vec<wgsl::Module> {
    let files: Vec<(&str, &str)> = wgsl::FILES
        .iter()
        .map(|&(n, t)| (n, if n == name { text } else { t }))
        .collect();
    wgsl::all_modules(&files)
}

#[test]
fn every_assembled_module_validates() {
    let modules = wgsl::all_modules(wgsl::FILES);
    // 4 scene kernel variants, each Whitted and path, the resolve, the
    // packing, the adaptive convergence test and the error-optimal mode's
    // allocation.
    assert_eq!(
        modules.len(),
        12,
        "{:?}",
        modules.iter().map(|m| &m.name).collect::<Vec<_>>()
    );
    validate::validate_all(&modules).unwrap();
}

#[test]
fn a_syntax_error_in_a_wgsl_file_is_refused() {
    let broken = format!("{}\nfn broken() {{\n    let x = ;\n}}\n", wgsl::FILES[0].1);
    let report = validate::validate_all(&modules_with(wgsl::FILES[0].0, &broken)).unwrap_err();
    assert!(report.contains("let x = ;"), "{report}");
    // Named by file and line, though the module is several files.
    let line = wgsl::FILES[0].1.lines().count() + 3;
    assert!(
        report.contains(&format!("{}:{line}: ", wgsl::FILES[0].0)),
        "{report}"
    );
}

#[test]
fn a_type_error_in_a_wgsl_file_is_refused() {
    let original = wgsl::FILES
        .iter()
        .find(|(n, _)| *n == "sampling.wgsl")
        .unwrap()
        .1;
    let broken = format!("{original}\nfn mistyped() -> u32 {{\n    return 1.5;\n}}\n");
    let report = validate::validate_all(&modules_with("sampling.wgsl", &broken)).unwrap_err();
    // sampling.wgsl is in every scene kernel: all eight are refused.
    assert_eq!(
        report
            .matches("invalid WGSL in module scene kernel")
            .count(),
        8,
        "{report}"
    );
    assert!(report.contains("return 1.5;"), "{report}");
    let line = original.lines().count() + 3;
    assert!(
        report.contains(&format!("sampling.wgsl:{line}: ")),
        "{report}"
    );
}

#[test]
fn bindings_are_declared_from_the_one_table() {
    let kernel = wgsl::Kernel::variants()[0].module(wgsl::FILES);
    // Declared by the table only: no .wgsl file writes a binding.
    for (name, text) in wgsl::FILES {
        assert!(!text.contains("@binding("), "{name} declares a binding");
    }
    assert!(
        kernel
            .text
            .contains("@group(0) @binding(13) var<storage, read> active_blocks: array<u32>;"),
        "{}",
        kernel.text
    );
    assert_eq!(wgsl::SCENE.binding("active_blocks"), 13);
    assert!(
        kernel.text.contains(
            "@group(2) @binding(0) var<storage, read_write> wave_args_out: array<u32, 3>;"
        )
    );
}

/// bvh.wgsl's `specialise` line: the traversal written once, generated a
/// second time for instanced meshes with `mesh_prim` for `hit_prim` (so
/// the world's traversal can call it without recursion), and a line
/// naming a function that does not exist fails the assembly.
#[test]
fn the_mesh_traversal_is_generated_from_the_worlds() {
    let kernel = wgsl::Kernel::variants()
        .into_iter()
        .find(|k| k.tree == wgsl::Tree::Static)
        .unwrap()
        .module(wgsl::FILES);
    let body = |name: &str| {
        let start = kernel.text.find(&format!("fn {name}(")).unwrap();
        let end = start + kernel.text[start..].find("\n}\n").unwrap();
        kernel.text[start..end].to_string()
    };
    let (world, mesh) = (body("tree_closest"), body("mesh_closest"));
    assert!(world.contains(" hit_prim(") && !world.contains("mesh_prim("));
    assert!(mesh.contains(" mesh_prim(") && !mesh.contains("hit_prim("));
    assert_eq!(
        world
            .replace("tree_closest", "mesh_closest")
            .replace("hit_prim", "mesh_prim"),
        mesh
    );
    // The generated text is located as bvh.wgsl's.
    let at = kernel.text.find("fn mesh_closest(").unwrap();
    assert_eq!(kernel.locate(at).0, "bvh.wgsl (generated mesh_closest)");

    let bvh = wgsl::FILES
        .iter()
        .find(|(n, _)| *n == "bvh.wgsl")
        .unwrap()
        .1;
    let broken = bvh.replace("specialise tree_closest as", "specialise tree_nearest as");
    let err = std::panic::catch_unwind(|| modules_with("bvh.wgsl", &broken)).unwrap_err();
    let msg = err.downcast_ref::<String>().unwrap();
    assert_eq!(
        msg,
        "WGSL: no function tree_nearest to specialise as mesh_closest"
    );
}
