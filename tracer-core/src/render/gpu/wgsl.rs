//! The WGSL modules the GPU backend compiles, assembled from the .wgsl
//! files in this folder. Included both by the crate (render::gpu) and by
//! tracer-core's build.rs (through `#[path]`), which parses and validates
//! every module assembled here with naga, so a syntax or type error in any
//! .wgsl file fails `cargo build`. Plain Rust: no wgpu, no naga.
//!
//! Imports are explicit: a file's leading `//! import NAME.wgsl` lines
//! name the files it uses. A module is its roots with everything they
//! import, each file once, after the files it imports. A few files are
//! alternatives the host picks per scene (the world's queries: analytic.wgsl
//! or accel.wgsl; the moving meshes' queries); the files that call them say
//! so in a `//! uses` line, and the host names the chosen one as a root.

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

/// An assembled module: its text and where each file starts in it.
#[derive(Clone, Debug)]
pub struct Module {
    pub name: String,
    pub text: String,
    /// (byte offset, file) in order of the text.
    pub parts: Vec<(usize, String)>,
}

impl Module {
    /// The file and 1-based line in it of byte `offset` of the text.
    pub fn locate(&self, offset: usize) -> (&str, usize) {
        let (start, file) = self
            .parts
            .iter()
            .rev()
            .find(|(start, _)| *start <= offset)
            .map_or((0, "(generated)"), |(s, f)| (*s, f.as_str()));
        let line = self.text[start..offset.min(self.text.len())]
            .matches('\n')
            .count()
            + 1;
        (file, line)
    }
}

/// The files a file's leading `//! import NAME` lines name.
pub fn imports(text: &str) -> impl Iterator<Item = &str> {
    text.lines()
        .take_while(|l| l.starts_with("//"))
        .filter_map(|l| l.strip_prefix("//! import "))
        .map(str::trim)
}

/// `roots` and every file they import, each once, each after its imports,
/// after `prelude` (generated constants). Panics on an import of a file
/// that does not exist or an import cycle: build.rs assembles every module
/// the backend can, so such a mistake fails the build.
pub fn assemble(files: &Files<'_>, name: &str, prelude: &str, roots: &[&str]) -> Module {
    fn visit(files: &Files<'_>, file: &str, open: &mut Vec<String>, m: &mut Module) {
        if m.parts.iter().any(|(_, f)| f == file) {
            return;
        }
        assert!(
            !open.iter().any(|f| f == file),
            "WGSL import cycle: {} -> {file}",
            open.join(" -> ")
        );
        let text = files
            .iter()
            .find(|(n, _)| *n == file)
            .unwrap_or_else(|| {
                panic!(
                    "WGSL: {} imports {file}, which does not exist",
                    open.last().map_or("the host", |s| s.as_str())
                )
            })
            .1;
        open.push(file.to_string());
        for dep in imports(text) {
            visit(files, dep, open, m);
        }
        open.pop();
        m.parts.push((m.text.len(), file.to_string()));
        m.text.push_str(text);
        m.text.push('\n');
    }
    let mut m = Module {
        name: name.to_string(),
        text: prelude.to_string(),
        parts: Vec::new(),
    };
    for root in roots {
        visit(files, root, &mut Vec::new(), &mut m);
    }
    m
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
        self.module(FILES).text
    }

    /// The kernel assembled from `files`.
    pub fn module(&self, files: &Files<'_>) -> Module {
        let mut roots = vec![match self.tree {
            Tree::Static => "accel.wgsl",
            Tree::None | Tree::MovingOnly => "analytic.wgsl",
        }];
        roots.push("wavefront.wgsl");
        match self.dist {
            Dist::MovingMeshes => roots.push("moving_meshes.wgsl"),
            Dist::Still => roots.push("no_moving_meshes.wgsl"),
            Dist::None => {}
        }
        assemble(
            files,
            &format!("scene kernel {:?}/{:?}", self.tree, self.dist),
            &format!(
                "const STACK_CAP: u32 = {}u;\nconst BVH_STACK: u32 = {}u;\n",
                self.stack_cap, self.bvh_stack
            ),
            &roots,
        )
    }
}

/// Sums to 8-bit sRGB (PNG) or linear f32 (EXR) on the GPU: one module, both kernels.
pub fn resolve_module(files: &Files<'_>) -> Module {
    assemble(files, "resolve", "", &["resolve_linear.wgsl"])
}

/// The farm's packing kernels.
pub fn pack_module(files: &Files<'_>) -> Module {
    assemble(files, "pack", "", &["pack.wgsl"])
}

/// Every module the backend compiles: what build.rs validates.
pub fn all_modules(files: &Files<'_>) -> Vec<Module> {
    let mut all: Vec<Module> = Kernel::variants().iter().map(|k| k.module(files)).collect();
    all.push(resolve_module(files));
    all.push(pack_module(files));
    all
}
