//! The compute pipelines: the WGSL assembled for a scene (only the
//! files its features need), specialised by overridable constants, and
//! the scene's buffers uploaded with it; the adaptive variant on first use.

use wgpu::util::DeviceExt as _;

use super::layout::{self, SceneData, TreeArray};
use super::wgsl::{self, Kernel, Tree};
use super::{GpuError, GpuRenderer, SceneState, Strategy, WavePipelines, check_size};
use crate::world::World;

/// Elements a piece of a tree's array is written in, and the bytes of
/// pieces submitted at once: wgpu stages each write until its submission
/// is done, so this bounds the host memory an upload takes however big
/// the mesh.
const TREE_PIECE: usize = 1 << 16;
const TREE_FLUSH_BYTES: u64 = 16 << 20;

impl GpuRenderer {
    /// The scene's buffers and its specialised pipelines. The pipelines of
    /// `old` (the scene rendered before) are kept when they would be made
    /// from the same source and constants: an animation's frames differ in
    /// the camera and the objects' places, not in the kernel, and compiling
    /// it again cost a frame more than tracing it. The tree's buffers are
    /// kept too when the tree is the same.
    pub(super) fn upload_scene(
        &self,
        data: SceneData,
        world: &World<f32>,
        limits: &wgpu::Limits,
        old: Option<SceneState>,
    ) -> Result<SceneState, GpuError> {
        let make = |label, bytes: &[u8], usage| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: bytes,
                    usage,
                })
        };
        let st = wgpu::BufferUsages::STORAGE;
        for (what, bytes) in [
            (
                "the scene's spheres",
                std::mem::size_of_val(data.spheres.as_slice()),
            ),
            (
                "the scene's planes",
                std::mem::size_of_val(data.planes.as_slice()),
            ),
            (
                "the scene's materials",
                std::mem::size_of_val(data.materials.as_slice()),
            ),
            (
                "the scene's lights",
                std::mem::size_of_val(data.lights.as_slice()),
            ),
            (
                // An environment image's texels and CDFs are most of it.
                "the scene's distributed and path data (an environment image: 20 bytes a texel)",
                data.dist
                    .as_ref()
                    .map_or(0, |d| std::mem::size_of_val(d.words.as_slice())),
            ),
            (
                "the scene's BVH nodes",
                data.tree
                    .as_ref()
                    .map_or(0, |t| t.layout.bytes(layout::TreeArray::Nodes) as usize),
            ),
            (
                "the scene's triangles",
                data.tree
                    .as_ref()
                    .map_or(0, |t| t.layout.bytes(layout::TreeArray::Triangles) as usize),
            ),
            (
                "the scene's triangle shading data",
                data.tree
                    .as_ref()
                    .map_or(0, |t| t.layout.bytes(layout::TreeArray::Shading) as usize),
            ),
            (
                "the scene's instances",
                data.tree
                    .as_ref()
                    .map_or(0, |t| std::mem::size_of_val(t.layout.instances.as_slice())),
            ),
            (
                "the scene's vertex attributes",
                data.pbr
                    .as_ref()
                    .map_or(0, |p| std::mem::size_of_val(p.vertices.as_slice())),
            ),
            (
                "the scene's attribute triangles",
                data.pbr
                    .as_ref()
                    .map_or(0, |p| std::mem::size_of_val(p.tri_attrs.as_slice())),
            ),
        ] {
            check_size(
                what,
                bytes as u64,
                limits.max_storage_buffer_binding_size,
                "max_storage_buffer_binding_size",
                "render the scene with --backend cpu, or on a GPU that allows larger buffers",
            )?;
        }
        if let Some(p) = &data.pbr {
            let needed = p.texture_bytes();
            let table = (layout::TEXEL_TABLES * 4) as u64;
            for (budget, budget_name) in [
                (super::TEXTURE_BUDGET, "the default, TEXTURE_BUDGET"),
                (
                    limits.max_storage_buffer_binding_size.saturating_sub(table),
                    "the adapter's max_storage_buffer_binding_size less the decode tables",
                ),
            ] {
                if needed > budget {
                    return Err(GpuError::TextureBudget {
                        needed,
                        budget,
                        budget_name,
                    });
                }
            }
        }
        let frame = make(
            "frame",
            bytemuck::bytes_of(&data.frame),
            wgpu::BufferUsages::UNIFORM,
        );
        let spheres = make("spheres", bytemuck::cast_slice(&data.spheres), st);
        let planes = make("planes", bytemuck::cast_slice(&data.planes), st);
        let materials = make("materials", bytemuck::cast_slice(&data.materials), st);
        let lights = make("lights", bytemuck::cast_slice(&data.lights), st);
        let n_moving_meshes = data.dist.as_ref().map_or(0, |d| d.n_moving_meshes);
        let kernel = Kernel {
            tree: match (&data.tree, data.static_tree) {
                (Some(_), true) => Tree::Static,
                (Some(_), false) => Tree::MovingOnly,
                (None, _) => Tree::None,
            },
            moving_meshes: n_moving_meshes > 0,
            stack_cap: data.stack_capacity(),
            // One more entry than these trees can need (checked at packing to
            // be at most bvh::STACK; see bvh.wgsl), so shallow trees keep small stacks.
            bvh_stack: data
                .tree
                .as_ref()
                .map_or(crate::bvh::STACK as u32, |t| t.layout.stack)
                + 1,
            path: data.path.is_some(),
        };
        let source = kernel.source();
        let b = |v: bool| if v { 1.0 } else { 0.0 };
        let constants = [
            ("N_SPHERES", data.n_spheres as f64),
            ("N_PLANES", data.n_planes as f64),
            ("N_LIGHTS", data.n_lights as f64),
            ("MAX_DEPTH", data.max_depth as f64),
            ("HAS_REFLECTION", b(data.has_reflection)),
            ("HAS_REFRACTION", b(data.has_refraction)),
            ("WG_X", self.options.workgroup.0 as f64),
            ("WG_Y", self.options.workgroup.1 as f64),
        ];
        // Model materials: left out for scenes without (their kernel is as before).
        let mut constants = constants.to_vec();
        if data.tree.as_ref().is_some_and(|t| t.layout.n_instances > 0) {
            constants.push(("HAS_INSTANCES", 1.0));
        }
        if let Some(p) = &data.pbr {
            constants.push(("HAS_PBR", 1.0));
            if p.cutouts {
                constants.push(("HAS_CUTOUTS", 1.0));
            }
        }
        let mut all_constants = constants.clone();
        if let Some(d) = &data.dist {
            all_constants.extend([
                ("DISTRIBUTED", 1.0),
                ("N_DLIGHTS", d.n_lights as f64),
                ("N_MOVING", d.n_moving as f64),
                ("HAS_LENS", b(d.has_lens)),
                ("HAS_BLUR", b(d.has_blur)),
                ("HAS_CAM_MOTION", b(d.has_camera_motion)),
            ]);
            if n_moving_meshes > 0 {
                all_constants.push(("N_MOVING_MESHES", n_moving_meshes as f64));
            }
        }
        if let Some(p) = &data.path {
            all_constants.extend([("PATH_BASE", p.base as f64), ("PATH_NEE", b(p.nee))]);
            if p.emitters > 0 {
                all_constants.extend([
                    ("PATH_EMITTERS", p.emitters as f64),
                    ("PATH_EMIT_BASE", p.emit_base as f64),
                ]);
            }
            if p.env_base > 0 {
                all_constants.push(("PATH_ENV_BASE", p.env_base as f64));
            }
        }
        let entry = wgsl::STACK_ENTRY;
        let old = old.filter(|o| o.options == self.options);
        let same_kernel = old
            .as_ref()
            .is_some_and(|o| o.source == source && o.constants == all_constants);
        let same_tree = old.as_ref().is_some_and(|o| o.data.tree == data.tree);
        // The same images (layout::TexelPack): their buffer is kept.
        let same_texels = old.as_ref().is_some_and(
            |o| matches!((&o.data.pbr, &data.pbr), (Some(a), Some(b)) if a.texels == b.texels),
        );
        // The same distributed words (every tile of a frame; an
        // environment image is most of them): their buffer is kept.
        let same_dist = old
            .as_ref()
            .is_some_and(|o| match (&o.data.dist, &data.dist) {
                (Some(a), Some(b)) => {
                    bytemuck::cast_slice::<_, u8>(&a.words)
                        == bytemuck::cast_slice::<_, u8>(&b.words)
                }
                _ => false,
            });
        let (kept_kernel, kept_tree, kept_texels, kept_dist) = match old {
            Some(o) => {
                let [_, _, _, _, texels] = o.pbr;
                (
                    same_kernel.then_some((o.module, o.pipeline, o.adaptive, o.wave)),
                    same_tree.then_some(o.tree),
                    same_texels.then_some(texels),
                    same_dist.then_some(o.dist),
                )
            }
            None => (None, None, None, None),
        };
        let dist = match (kept_dist, &data.dist) {
            (Some(kept), _) => kept,
            (None, Some(d)) => {
                self.dist_uploads
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                make("distributed", bytemuck::cast_slice(&d.words), st)
            }
            (None, None) => make("distributed", &[0u8; 64], st),
        };
        let pbr = match &data.pbr {
            Some(p) => [
                make("material pbr", bytemuck::cast_slice(&p.mat_pbr), st),
                make("pbr materials", bytemuck::cast_slice(&p.pbrs), st),
                make(
                    "attribute triangles",
                    bytemuck::cast_slice(&p.tri_attrs),
                    st,
                ),
                make("vertex attributes", bytemuck::cast_slice(&p.vertices), st),
                match kept_texels {
                    Some(t) => t,
                    None => {
                        self.texel_uploads
                            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        make("texels", bytemuck::cast_slice(&p.texels.words), st)
                    }
                },
            ],
            None => [
                "material pbr",
                "pbr materials",
                "attribute triangles",
                "vertex attributes",
                "texels",
            ]
            .map(|label| make(label, &[0u8; 512], st)),
        };
        let tree = match kept_tree {
            Some(t) => t,
            None => match &data.tree {
                Some(t) => {
                    let [nodes, prims, triangles, shading] = self.write_tree(world, &t.layout)?;
                    let instances =
                        make("instances", bytemuck::cast_slice(&t.layout.instances), st);
                    [nodes, prims, triangles, shading, instances]
                }
                None => [
                    "bvh nodes",
                    "bvh prims",
                    "triangles",
                    "triangle shading",
                    "instances",
                ]
                .map(|label| make(label, &[0u8; 128], st)),
            },
        };
        let (module, pipeline, adaptive, wave) = match kept_kernel {
            Some(k) => k,
            None => {
                let module = self
                    .device
                    .create_shader_module(wgpu::ShaderModuleDescriptor {
                        label: Some("tessera scene kernel"),
                        source: wgpu::ShaderSource::Wgsl(source.as_str().into()),
                    });
                let pipeline =
                    self.device
                        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                            label: Some(entry),
                            layout: Some(&self.pipeline_layout),
                            module: &module,
                            entry_point: Some(entry),
                            compilation_options: wgpu::PipelineCompilationOptions {
                                constants: &all_constants,
                                // Only the ray counters live in workgroup memory, and WGSL zeroes them anyway.
                                zero_initialize_workgroup_memory: true,
                            },
                            cache: self.pipeline_cache(),
                        });
                // Whitted's distributed effects run on the stack kernel only;
                // the path integrator has a wavefront of its own (path_wave.wgsl).
                let wave = (self.options.strategy == Strategy::Wavefront
                    && (data.dist.is_none() || kernel.path))
                    .then(|| {
                        let task_bytes = if kernel.path {
                            layout::PATH_WAVE_TASK_BYTES
                        } else {
                            layout::WAVE_TASK_BYTES
                        };
                        // Twice the largest dispatch's primary tasks, within one indirect dispatch.
                        let (wx, wy) = self.options.workgroup;
                        let max_groups = limits.max_compute_workgroups_per_dimension as u64;
                        let queue_cap = (2 * self.options.dispatch_pixel_samples)
                            .min(max_groups * (wx * wy) as u64)
                            .min(limits.max_storage_buffer_binding_size / task_bytes);
                        let mut wave_constants = all_constants.clone();
                        wave_constants.push(("QUEUE_CAP", queue_cap as f64));
                        let make = |entry: &str, layout: &wgpu::PipelineLayout| {
                            self.device
                                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                                    label: Some(entry),
                                    layout: Some(layout),
                                    module: &module,
                                    entry_point: Some(entry),
                                    compilation_options: wgpu::PipelineCompilationOptions {
                                        constants: &wave_constants,
                                        zero_initialize_workgroup_memory: true,
                                    },
                                    cache: self.pipeline_cache(),
                                })
                        };
                        let (primary, shade) = if kernel.path {
                            ("path_wave_primary", "path_wave_shade")
                        } else {
                            ("wave_primary", "wave_shade")
                        };
                        WavePipelines {
                            primary: make(primary, &self.wave_pipeline_layout),
                            swap: make("wave_swap", &self.wave_swap_layout),
                            shade: make(shade, &self.wave_pipeline_layout),
                            queue_cap,
                            task_bytes,
                        }
                    });
                self.pipelines_built
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if let Some(c) = &self.disk_cache {
                    c.save();
                }
                (module, pipeline, None, wave)
            }
        };
        Ok(SceneState {
            data,
            options: self.options,
            pipeline,
            module,
            source,
            constants: all_constants,
            adaptive,
            frame,
            spheres,
            planes,
            materials,
            lights,
            tree,
            dist,
            pbr,
            wave,
        })
    }

    /// The arrays of `world`'s trees laid out as `layout` (`SceneData::tree`),
    /// written to new buffers in pieces ([`layout::TreePack::write`]), a
    /// submission every [`TREE_FLUSH_BYTES`]: the host never holds them
    /// whole (a 10 M-triangle mesh's are 1.3 GB).
    fn write_tree(
        &self,
        world: &World<f32>,
        layout: &layout::TreeLayout,
    ) -> Result<[wgpu::Buffer; 4], GpuError> {
        let pack = SceneData::tree_pack(world)?
            .filter(|p| p.layout == *layout)
            .ok_or_else(|| {
                GpuError::BadTree(
                    "the world's trees are not those its scene data was packed from".into(),
                )
            })?;
        let buffers = TreeArray::ALL.map(|array| {
            self.buffer(
                match array {
                    TreeArray::Nodes => "bvh nodes",
                    TreeArray::Prims => "bvh prims",
                    TreeArray::Triangles => "triangles",
                    TreeArray::Shading => "triangle shading",
                },
                layout.bytes(array),
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            )
        });
        self.tree_uploads
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut staged = 0u64;
        pack.write(TREE_PIECE, |array, at, bytes| {
            let offset = (at * array.element_bytes()) as u64;
            self.queue
                .write_buffer(&buffers[array as usize], offset, bytes);
            staged += bytes.len() as u64;
            if staged >= TREE_FLUSH_BYTES {
                staged = 0;
                self.wait(self.queue.submit([]))?;
            }
            Ok::<(), GpuError>(())
        })?;
        Ok(buffers)
    }

    /// The scene's kernel for adaptive rounds: its pipeline with `ADAPTIVE`.
    pub(super) fn adaptive_pipeline(&self, scene: &SceneState) -> wgpu::ComputePipeline {
        let mut constants = scene.constants.clone();
        constants.push(("ADAPTIVE", 1.0));
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("tessera adaptive"),
                layout: Some(&self.pipeline_layout),
                module: &scene.module,
                entry_point: Some(wgsl::STACK_ENTRY),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    zero_initialize_workgroup_memory: true,
                },
                cache: self.pipeline_cache(),
            });
        if let Some(c) = &self.disk_cache {
            c.save();
        }
        pipeline
    }
}
