//! The WGSL modules the GPU backend compiles, assembled from the .wgsl
//! files in this folder. Included both by the crate (render::gpu) and by
//! tracer-core's build.rs (through `#[path]`), which parses and validates
//! every module assembled here with naga, so a syntax or type error in any
//! .wgsl file fails `cargo build`. Plain Rust: no wgpu, no naga.

/// Every .wgsl file, by name.
pub const FILES: &[(&str, &str)] = &[
    ("accel.wgsl", include_str!("accel.wgsl")),
    ("analytic.wgsl", include_str!("analytic.wgsl")),
    ("bvh.wgsl", include_str!("bvh.wgsl")),
    ("distributed.wgsl", include_str!("distributed.wgsl")),
    ("moving_meshes.wgsl", include_str!("moving_meshes.wgsl")),
    (
        "no_moving_meshes.wgsl",
        include_str!("no_moving_meshes.wgsl"),
    ),
    ("pack.wgsl", include_str!("pack.wgsl")),
    ("resolve.wgsl", include_str!("resolve.wgsl")),
    ("resolve_linear.wgsl", include_str!("resolve_linear.wgsl")),
    ("sampling.wgsl", include_str!("sampling.wgsl")),
    ("wavefront.wgsl", include_str!("wavefront.wgsl")),
    ("whitted.wgsl", include_str!("whitted.wgsl")),
    ("wide_int.wgsl", include_str!("wide_int.wgsl")),
];

/// A set of .wgsl files by name: [`FILES`], or (in tests of the
/// build-time check) a copy with one file broken.
pub type Files<'a> = [(&'a str, &'a str)];

/// The text of the file `name` in `files` ("" for none).
fn file<'a>(files: &Files<'a>, name: &str) -> &'a str {
    files
        .iter()
        .find(|(n, _)| *n == name)
        .map_or("", |(_, text)| text)
}

/// How the scene kernel's world is queried.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Tree {
    /// No tree: loops over spheres and planes (analytic.wgsl).
    None,
    /// A tree over the static world (bvh.wgsl, accel.wgsl).
    Static,
    /// Trees of moving meshes only; the static world by loops.
    MovingOnly,
}

/// The scene kernel's distributed effects.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dist {
    None,
    /// Distributed effects without moving meshes.
    Still,
    /// With moving meshes (needs a tree: `Tree::Static` or `Tree::MovingOnly`).
    MovingMeshes,
}

/// One variant of the scene kernel, as the host picks it for a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Kernel {
    pub tree: Tree,
    pub dist: Dist,
    /// Entries of the per-thread task stack (layout.rs `stack_capacity`).
    pub stack_cap: u32,
    /// Entries of the BVH traversal stack (at most bvh::STACK + 1).
    pub bvh_stack: u32,
}

impl Kernel {
    /// Every variant the host can assemble (with small stacks): what
    /// build.rs validates.
    pub fn variants() -> Vec<Kernel> {
        let mut all = Vec::new();
        for tree in [Tree::None, Tree::Static, Tree::MovingOnly] {
            for dist in [Dist::None, Dist::Still, Dist::MovingMeshes] {
                let possible = match (tree, dist) {
                    (Tree::None, Dist::MovingMeshes) => false,
                    (Tree::MovingOnly, d) => d == Dist::MovingMeshes,
                    _ => true,
                };
                if possible {
                    all.push(Kernel {
                        tree,
                        dist,
                        stack_cap: 2,
                        bvh_stack: 25,
                    });
                }
            }
        }
        all
    }

    /// The kernel's WGSL. Its stacks' capacities must be constant
    /// expressions, so they lead the text; only scenes with a tree (their
    /// own or a moving mesh's) compile the BVH traversal, and only those
    /// with distributed effects their kernel.
    pub fn source(&self) -> String {
        self.source_in(FILES)
    }

    /// [`Kernel::source`] from `files`.
    pub fn source_in(&self, files: &Files<'_>) -> String {
        let (traversal, queries) = match self.tree {
            Tree::Static => ("bvh.wgsl", "accel.wgsl"),
            Tree::MovingOnly => ("bvh.wgsl", "analytic.wgsl"),
            Tree::None => ("", "analytic.wgsl"),
        };
        let (distributed, moving_meshes) = match self.dist {
            Dist::MovingMeshes => ("distributed.wgsl", "moving_meshes.wgsl"),
            Dist::Still => ("distributed.wgsl", "no_moving_meshes.wgsl"),
            Dist::None => ("", ""),
        };
        format!(
            "const STACK_CAP: u32 = {}u;\nconst BVH_STACK: u32 = {}u;\n{}\n{}\n{}\n{}\n{}\n{}\n{}\n{}",
            self.stack_cap,
            self.bvh_stack,
            file(files, "sampling.wgsl"),
            file(files, "wide_int.wgsl"),
            file(files, "whitted.wgsl"),
            file(files, traversal),
            file(files, queries),
            file(files, "wavefront.wgsl"),
            file(files, distributed),
            file(files, moving_meshes),
        )
    }
}

/// Sums to 8-bit sRGB (PNG) or linear f32 (EXR) on the GPU: one module, both kernels.
pub fn resolve_source(files: &Files<'_>) -> String {
    [
        file(files, "resolve.wgsl"),
        file(files, "wide_int.wgsl"),
        file(files, "resolve_linear.wgsl"),
    ]
    .concat()
}

/// The farm's packing kernels.
pub fn pack_source(files: &Files<'_>) -> String {
    file(files, "pack.wgsl").to_string()
}

/// Every module the backend compiles, named: what build.rs validates.
pub fn all_modules(files: &Files<'_>) -> Vec<(String, String)> {
    let mut all: Vec<(String, String)> = Kernel::variants()
        .into_iter()
        .map(|k| {
            (
                format!("scene kernel {:?}/{:?}", k.tree, k.dist),
                k.source_in(files),
            )
        })
        .collect();
    all.push(("resolve".into(), resolve_source(files)));
    all.push(("pack".into(), pack_source(files)));
    all
}
