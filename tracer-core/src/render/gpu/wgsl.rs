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
//!
//! A file's `//! specialise F as G: A -> B` lines generate, after the
//! file, function `G`: `F`'s text with every call of `A` made a call of
//! `B` (bvh.wgsl's traversal for the world's tree and for an instanced
//! mesh's, as Rust instantiates one generic function twice; WGSL has
//! neither generics nor recursion).
//!
//! Each bind group layout is declared once, below ([`SCENE`] and kin):
//! the host's layout entries and binding numbers and the WGSL `var`
//! declarations (generated after the file that uses each binding) come
//! from that one table, so they cannot disagree.

/// The stack driver's entry point (stack.wgsl), for either integrator.
pub const STACK_ENTRY: &str = "render";

/// Every .wgsl file, by name.
pub const FILES: &[(&str, &str)] = &[
    ("accel.wgsl", include_str!("accel.wgsl")),
    ("allocate.wgsl", include_str!("allocate.wgsl")),
    ("analytic.wgsl", include_str!("analytic.wgsl")),
    ("bsdf.wgsl", include_str!("bsdf.wgsl")),
    ("bvh.wgsl", include_str!("bvh.wgsl")),
    ("converge.wgsl", include_str!("converge.wgsl")),
    ("distributed.wgsl", include_str!("distributed.wgsl")),
    ("geometry.wgsl", include_str!("geometry.wgsl")),
    ("instances.wgsl", include_str!("instances.wgsl")),
    ("moving_meshes.wgsl", include_str!("moving_meshes.wgsl")),
    (
        "no_moving_meshes.wgsl",
        include_str!("no_moving_meshes.wgsl"),
    ),
    ("pack.wgsl", include_str!("pack.wgsl")),
    ("path.wgsl", include_str!("path.wgsl")),
    ("path_wave.wgsl", include_str!("path_wave.wgsl")),
    ("pbr.wgsl", include_str!("pbr.wgsl")),
    ("resolve.wgsl", include_str!("resolve.wgsl")),
    ("resolve_linear.wgsl", include_str!("resolve_linear.wgsl")),
    ("sampling.wgsl", include_str!("sampling.wgsl")),
    ("scene.wgsl", include_str!("scene.wgsl")),
    ("shade.wgsl", include_str!("shade.wgsl")),
    ("stack.wgsl", include_str!("stack.wgsl")),
    ("sums.wgsl", include_str!("sums.wgsl")),
    ("wave_queue.wgsl", include_str!("wave_queue.wgsl")),
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
    #[allow(dead_code)] // build.rs's reports
    pub name: String,
    pub text: String,
    /// (byte offset, file) in order of the text.
    pub parts: Vec<(usize, String)>,
}

impl Module {
    /// The file and 1-based line in it of byte `offset` of the text.
    #[allow(dead_code)] // build.rs's reports
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

/// The file's `//! specialise F as G: A -> B` lines, as (F, G, A, B).
pub fn specialisations(text: &str) -> impl Iterator<Item = [&str; 4]> {
    text.lines()
        .take_while(|l| l.starts_with("//"))
        .filter_map(|l| l.strip_prefix("//! specialise "))
        .map(|l| {
            let parse = || {
                let (f, rest) = l.split_once(" as ")?;
                let (g, rest) = rest.split_once(':')?;
                let (a, b) = rest.split_once("->")?;
                Some([f, g, a, b].map(str::trim))
            };
            parse().unwrap_or_else(|| panic!("WGSL: malformed line `//! specialise {l}`"))
        })
}

/// Function `f` of `text` (from `fn f(` to its closing brace) renamed `g`,
/// with each call of `a` made a call of `b`. Panics where `text` has no
/// such function: build.rs assembles every module, so the build fails.
pub fn specialise(text: &str, [f, g, a, b]: [&str; 4]) -> String {
    let head = format!("fn {f}(");
    let start = text
        .find(&head)
        .unwrap_or_else(|| panic!("WGSL: no function {f} to specialise as {g}"));
    let mut depth = 0;
    let mut end = None;
    for (i, c) in text[start..].char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    end = Some(start + i + 1);
                    break;
                }
            }
            _ => {}
        }
    }
    let body = &text[start..end.unwrap_or_else(|| panic!("WGSL: function {f} never closes"))];
    let call = format!("{a}(");
    assert!(body.contains(&call), "WGSL: {f} never calls {a}");
    format!(
        "// {f} with {b} for {a} (generated: a `specialise` line)\n{}\n",
        body.replacen(&head, &format!("fn {g}("), 1)
            .replace(&format!(" {call}"), &format!(" {b}("))
            .replace(&format!("({call}"), &format!("({b}("))
    )
}

/// `roots` and every file they import, each once, each after its imports,
/// after `prelude` (generated constants). Panics on an import of a file
/// that does not exist or an import cycle: build.rs assembles every module
/// the backend can, so such a mistake fails the build.
/// Each file's bindings in `layouts` are declared right after it.
pub fn assemble(
    files: &Files<'_>,
    layouts: &[Layout],
    name: &str,
    prelude: &str,
    roots: &[&str],
) -> Module {
    fn visit(
        files: &Files<'_>,
        layouts: &[Layout],
        file: &str,
        open: &mut Vec<String>,
        m: &mut Module,
    ) {
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
            visit(files, layouts, dep, open, m);
        }
        open.pop();
        m.parts.push((m.text.len(), file.to_string()));
        m.text.push_str(text);
        m.text.push('\n');
        for spec in specialisations(text) {
            m.parts
                .push((m.text.len(), format!("{file} (generated {})", spec[1])));
            m.text.push_str(&specialise(text, spec));
        }
        // The file's bindings, generated from their one declaration.
        for layout in layouts {
            m.text.push_str(&layout.declarations(file));
        }
    }
    let mut m = Module {
        name: name.to_string(),
        text: prelude.to_string(),
        parts: Vec::new(),
    };
    for root in roots {
        visit(files, layouts, root, &mut Vec::new(), &mut m);
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

/// One variant of the scene kernel, as the host picks it for a scene.
/// Distributed effects are pipeline overrides (distributed.wgsl), not
/// files: every scene's kernel has them, off by default.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Kernel {
    pub tree: Tree,
    /// Moving meshes' queries (moving_meshes.wgsl; needs a tree:
    /// `Tree::Static` or `Tree::MovingOnly`), else their stand-ins.
    pub moving_meshes: bool,
    /// Entries of the per-thread task stack (layout.rs `stack_capacity`).
    pub stack_cap: u32,
    /// Entries of the BVH traversal stack (at most bvh::STACK + 1).
    pub bvh_stack: u32,
    /// The path integrator's kernel (path.wgsl and path_wave.wgsl)
    /// instead of the Whitted drivers.
    pub path: bool,
}

impl Kernel {
    /// Every variant the host can assemble (with small stacks): what
    /// build.rs validates.
    #[allow(dead_code)] // build.rs
    pub fn variants() -> Vec<Kernel> {
        [
            (Tree::None, false),
            (Tree::Static, false),
            (Tree::Static, true),
            (Tree::MovingOnly, true),
        ]
        .into_iter()
        .flat_map(|(tree, moving_meshes)| {
            [false, true].map(|path| Kernel {
                tree,
                moving_meshes,
                stack_cap: 2,
                bvh_stack: 25,
                path,
            })
        })
        .collect()
    }

    /// The kernel's WGSL. Its stacks' capacities must be constant
    /// expressions, so they lead the text; only scenes with a tree (their
    /// own or a moving mesh's) compile the BVH traversal.
    pub fn source(&self) -> String {
        self.module(FILES).text
    }

    /// The kernel assembled from `files`: the world's queries, the stack
    /// and wavefront drivers (with the shading step they share), the
    /// moving meshes' queries.
    pub fn module(&self, files: &Files<'_>) -> Module {
        let queries = match self.tree {
            Tree::Static => "accel.wgsl",
            Tree::None | Tree::MovingOnly => "analytic.wgsl",
        };
        let moving = if self.moving_meshes {
            "moving_meshes.wgsl"
        } else {
            "no_moving_meshes.wgsl"
        };
        assemble(
            files,
            &[SCENE, WAVE_QUEUES, WAVE_ARGS],
            &format!(
                "scene kernel {:?}{}{}",
                self.tree,
                if self.moving_meshes {
                    "+moving meshes"
                } else {
                    ""
                },
                if self.path { "+path" } else { "" }
            ),
            &format!(
                "const STACK_CAP: u32 = {}u;\nconst BVH_STACK: u32 = {}u;\n",
                self.stack_cap, self.bvh_stack
            ),
            &if self.path {
                vec![queries, "path.wgsl", "path_wave.wgsl", moving]
            } else {
                vec![queries, "whitted.wgsl", "wavefront.wgsl", moving]
            },
        )
    }
}

/// Sums to 8-bit sRGB (PNG) or linear f32 (EXR) on the GPU: one module, both kernels.
pub fn resolve_module(files: &Files<'_>) -> Module {
    assemble(files, &[RESOLVE], "resolve", "", &["resolve_linear.wgsl"])
}

/// The farm's packing kernels.
pub fn pack_module(files: &Files<'_>) -> Module {
    assemble(files, &[PACK], "pack", "", &["pack.wgsl"])
}

/// An adaptive render's convergence test, between rounds on the GPU.
pub fn converge_module(files: &Files<'_>) -> Module {
    assemble(files, &[CONVERGE], "converge", "", &["converge.wgsl"])
}

/// The error-optimal mode's decision between its rounds on the GPU.
pub fn allocate_module(files: &Files<'_>) -> Module {
    assemble(files, &[ALLOCATE], "allocate", "", &["allocate.wgsl"])
}

/// Every module the backend compiles: what build.rs validates.
#[allow(dead_code)] // build.rs
pub fn all_modules(files: &Files<'_>) -> Vec<Module> {
    let mut all: Vec<Module> = Kernel::variants().iter().map(|k| k.module(files)).collect();
    all.push(resolve_module(files));
    all.push(pack_module(files));
    all.push(converge_module(files));
    all.push(allocate_module(files));
    all
}

/// How a binding's buffer is bound.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    Uniform,
    /// A uniform buffer bound at a dynamic offset (a dispatch's parameters).
    UniformDynamic,
    Read,
    ReadWrite,
}

/// One buffer binding: its WGSL name and type, how it is bound, and the
/// file that uses it (its declaration is generated into every module that
/// includes that file).
#[derive(Clone, Copy, Debug)]
pub struct Binding {
    pub name: &'static str,
    pub ty: &'static str,
    pub access: Access,
    pub file: &'static str,
}

/// A bind group's layout, declared once: binding i is `bindings[i]`. The
/// host's bind group layout entries (render::gpu `layout_entries`), its
/// bind groups' binding numbers ([`Layout::binding`]) and the WGSL
/// `@group(g) @binding(i) var` declarations all come from it.
#[derive(Clone, Copy, Debug)]
pub struct Layout {
    pub group: u32,
    pub bindings: &'static [Binding],
}

impl Layout {
    /// The binding number of `name`. Panics on a name the layout lacks: a
    /// mistake in the host's code, which every GPU test would hit.
    pub fn binding(&self, name: &str) -> u32 {
        self.bindings
            .iter()
            .position(|b| b.name == name)
            .unwrap_or_else(|| panic!("no binding {name} in group {}", self.group)) as u32
    }

    /// The WGSL declarations of the bindings `file` uses.
    fn declarations(&self, file: &str) -> String {
        let mut out = String::new();
        for (i, b) in self.bindings.iter().enumerate() {
            if b.file == file {
                let space = match b.access {
                    Access::Uniform | Access::UniformDynamic => "uniform",
                    Access::Read => "storage, read",
                    Access::ReadWrite => "storage, read_write",
                };
                out.push_str(&format!(
                    "@group({}) @binding({i}) var<{space}> {}: {};\n",
                    self.group, b.name, b.ty
                ));
            }
        }
        out
    }
}

const fn bind(name: &'static str, ty: &'static str, access: Access, file: &'static str) -> Binding {
    Binding {
        name,
        ty,
        access,
        file,
    }
}

use Access::{Read, ReadWrite, Uniform, UniformDynamic};

/// The scene kernel's group 0.
pub const SCENE: Layout = Layout {
    group: 0,
    bindings: &[
        bind("frame", "Frame", Uniform, "scene.wgsl"),
        bind("params", "Dispatch", UniformDynamic, "scene.wgsl"),
        bind("spheres", "array<Sphere>", Read, "scene.wgsl"),
        bind("planes", "array<Plane>", Read, "scene.wgsl"),
        bind("materials", "array<Material>", Read, "scene.wgsl"),
        bind("lights", "array<Light>", Read, "scene.wgsl"),
        bind("sums", "array<atomic<u32>>", ReadWrite, "scene.wgsl"),
        bind(
            "counters",
            "array<atomic<u32>, 10>",
            ReadWrite,
            "scene.wgsl",
        ),
        // The BVH: nodes, leaf references, triangles, triangle shading.
        bind("nodes", "array<BvhNode4>", Read, "bvh.wgsl"),
        bind("prims", "array<u32>", Read, "bvh.wgsl"),
        bind("triangles", "array<Triangle>", Read, "bvh.wgsl"),
        bind("shading", "array<TriangleShading>", Read, "bvh.wgsl"),
        // Distributed effects (layout.rs DistData; a placeholder without).
        bind("dist", "array<vec4<f32>>", Read, "distributed.wgsl"),
        // An adaptive round's active blocks, each (column | row << 16) in
        // blocks of 8x8 pixels from the film's corner (a placeholder otherwise).
        bind("active_blocks", "array<u32>", Read, "scene.wgsl"),
        // A ranged adaptive render's listed blocks (a placeholder
        // otherwise): each (first sample, end, first item, 0), then one
        // entry whose third word is the items in all (sums.wgsl
        // listed_work).
        bind("block_ranges", "array<vec4<u32>>", Read, "scene.wgsl"),
        // A ranged render's rays per listed block, (low, high) words,
        // added by stack.wgsl's listed dispatches (a placeholder
        // otherwise): the blocks' measured costs.
        bind("block_rays", "array<atomic<u32>>", ReadWrite, "scene.wgsl"),
        // Model files' materials (layout.rs PbrData; placeholders without).
        bind("mat_pbr", "array<u32>", Read, "pbr.wgsl"),
        bind("pbrs", "array<Pbr>", Read, "pbr.wgsl"),
        bind("tri_attrs", "array<u32>", Read, "pbr.wgsl"),
        bind("vertex_attrs", "array<VertexAttr>", Read, "pbr.wgsl"),
        bind("texels", "array<u32>", Read, "pbr.wgsl"),
        // Instanced meshes' placements (a placeholder without).
        bind("instances", "array<Instance>", Read, "instances.wgsl"),
    ],
};

/// The wavefront's task queues (group 1 of its passes).
pub const WAVE_QUEUES: Layout = Layout {
    group: 1,
    bindings: &[
        bind("queue_in", "array<WaveTask>", Read, "wave_queue.wgsl"),
        bind("queue_out", "array<WaveTask>", ReadWrite, "wave_queue.wgsl"),
        bind("wave", "WaveState", ReadWrite, "wave_queue.wgsl"),
    ],
};

/// Indirect dispatch arguments of the next wavefront shade pass: a group
/// of its own, which only wave_swap's layout has, because a buffer may not
/// be both written by and the indirect argument of one dispatch.
pub const WAVE_ARGS: Layout = Layout {
    group: 2,
    bindings: &[bind(
        "wave_args_out",
        "array<u32, 3>",
        ReadWrite,
        "wave_queue.wgsl",
    )],
};

/// The GPU resolve (resolve.wgsl and resolve_linear.wgsl).
pub const RESOLVE: Layout = Layout {
    group: 0,
    bindings: &[
        bind("params", "ResolveParams", Uniform, "resolve.wgsl"),
        // (low, high) u32 words of each channel's u64 sum, 6 words a pixel.
        bind("sums", "array<u32>", Read, "resolve.wgsl"),
        // resolve_srgb8 only. thresholds[k]: the smallest sum (low, high)
        // whose code is k + 1, k < 255.
        bind("thresholds", "array<vec2<u32>, 255>", Read, "resolve.wgsl"),
        // resolve_srgb8: RGB bytes, row-major, packed four to a word
        // (little-endian): 4 pixels make 3 words, so the read-back is the
        // image as the PNG encoder wants it. resolve_linear: the f32 bits of
        // R, G and B, 3 words a pixel.
        bind("image", "array<u32>", ReadWrite, "resolve.wgsl"),
    ],
};

/// The farm's packing (pack.wgsl).
pub const PACK: Layout = Layout {
    group: 0,
    bindings: &[
        bind("params", "PackParams", Uniform, "pack.wgsl"),
        // (low, high) u32 words of each channel's u64 sum, 6 words a pixel.
        bind("sums", "array<u32>", Read, "pack.wgsl"),
        // The film's width in bytes: the maximum over its sums (cleared to 0 first).
        bind("width", "atomic<u32>", ReadWrite, "pack.wgsl"),
        // The packed bytes, four to a word (little-endian); 4 pixels make 3 * width words.
        bind("packed", "array<u32>", ReadWrite, "pack.wgsl"),
    ],
};

/// The convergence test between the rounds of an adaptive render on the
/// GPU (converge.wgsl).
pub const CONVERGE: Layout = Layout {
    group: 0,
    bindings: &[
        bind("params", "ConvergeParams", Uniform, "converge.wgsl"),
        // The film's sums in the adaptive layout, 18 words a pixel.
        bind("sums", "array<u32>", Read, "converge.wgsl"),
        // Every block of the film, (column | row << 16), bit 31 set once
        // the block has converged: the trace kernel's `active_blocks`.
        bind("active_blocks", "array<u32>", ReadWrite, "converge.wgsl"),
        // Per block, after its last round: the f32 bits of the sum of its
        // pixels' variances of the mean (finite ones), of its worst error
        // ratio, its samples, and (ranged: the error-optimal mode) of the
        // sum of its pixels' channel means (render::adaptive's summaries).
        bind(
            "block_stats",
            "array<vec4<u32>>",
            ReadWrite,
            "converge.wgsl",
        ),
        // Ranged (`ConvergeParams::ranged`): every block's (first, end,
        // ..) sample of its last round, the trace kernel's `block_ranges`;
        // its pixels have `end` samples. Else unread.
        bind("count_ranges", "array<vec4<u32>>", Read, "converge.wgsl"),
    ],
};

/// The error-optimal mode's decision between its rounds on the GPU
/// (allocate.wgsl).
pub const ALLOCATE: Layout = Layout {
    group: 0,
    bindings: &[
        bind("params", "AllocateParams", Uniform, "allocate.wgsl"),
        // converge.wgsl's `block_stats` (ranged).
        bind("block_stats", "array<vec4<u32>>", Read, "allocate.wgsl"),
        // The trace kernel's `block_ranges` over every block of the film:
        // read as the round's, written as the next round's.
        bind("ranges", "array<vec4<u32>>", ReadWrite, "allocate.wgsl"),
        // The next round's slices' indirect dispatch arguments, three
        // words each.
        bind("dispatch_args", "array<u32>", ReadWrite, "allocate.wgsl"),
        // One entry a round (layout.rs RoundLog).
        bind("round_log", "array<RoundLog>", ReadWrite, "allocate.wgsl"),
        // The trace kernel's `block_rays`: each block's rays so far,
        // (low, high) words.
        bind("block_rays", "array<u32>", Read, "allocate.wgsl"),
    ],
};
