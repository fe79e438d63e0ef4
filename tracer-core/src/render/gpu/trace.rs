//! One render on the GPU: clear, the planned dispatches in bounded
//! submissions (the stack kernel, or the wavefront's generations), and the
//! read-back of sums and counters into a film (or the resolved image).

use std::time::{Duration, Instant};

use super::grid::Grid;
use super::layout::{self, COUNTERS, DispatchParams, GpuBlockStats, SUM_WORDS, SceneData};
use super::plan::{listed_groups, plan, plan_listed};
use super::readback::linear_pixels;
use super::wgsl;
use super::{
    GpuError, GpuOptions, GpuRenderer, GpuStats, LinearImage, Outputs, PARAMS_SLOTS, PARAMS_STRIDE,
    PackedSums, Readout, Rendered, Resolve, SceneState, Srgb8Image, WaveBuffers, WavePipelines,
    check_size, entire, params_bytes, sized,
};
use crate::film::{Film, RayCounts, Rect, SampleRange};

/// Which driver a render's dispatches run: the stack kernel (its plain or
/// adaptive pipeline), or the wavefront's passes with its queues and their
/// two bind groups.
enum Driver<'a> {
    Stack(&'a wgpu::ComputePipeline),
    Wave(
        &'a WavePipelines,
        &'a WaveBuffers,
        &'a (wgpu::BindGroup, wgpu::BindGroup),
    ),
}

/// A render's timestamp queries: a begin and an end per submission.
struct Timestamps {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
    count: u32,
}

impl GpuRenderer {
    /// One render: the scene's state, the grid, the planned dispatches in
    /// bounded submissions (a resident adaptive render's rounds chained,
    /// `converge.rs`), then the read-back. `None`: the wavefront's queues
    /// overflowed, and the caller renders again in smaller dispatches.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn render_inner(
        &self,
        data: SceneData,
        world: &crate::world::World<f32>,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
        start: Instant,
        budget: u64,
        readout: Readout<'_>,
    ) -> Result<Option<Rendered>, GpuError> {
        let limits = self.device.limits();
        let grid = Grid::new(&self.device, readout, rect);
        let mut scene_guard = self
            .scene
            .lock()
            .map_err(|_| GpuError::Device("scene cache poisoned".into()))?;
        if scene_guard
            .as_ref()
            .is_none_or(|s| s.data != data || s.options != self.options)
        {
            let old = scene_guard.take();
            *scene_guard = Some(self.upload_scene(data, world, &limits, old)?);
        }
        if grid.mask.is_some() {
            let scene = scene_guard.as_mut().expect("just set");
            if scene.adaptive.is_none() {
                scene.adaptive = Some(self.adaptive_pipeline(scene));
            }
        }
        let scene = scene_guard.as_ref().expect("just set");
        let resident = match readout {
            Readout::Resident(r) => Some(r),
            _ => None,
        };
        // A resident adaptive render runs all its rounds here; any other
        // render is one range of samples.
        let rounds = resident.map_or_else(|| vec![samples], |r| r.settings.rounds());

        let pixels = rect.area();
        let stride = grid.sum_words();
        let sums_bytes = (pixels * stride * 4) as u64;
        for limit in [
            (
                limits.max_storage_buffer_binding_size,
                "max_storage_buffer_binding_size",
            ),
            (limits.max_buffer_size, "max_buffer_size"),
        ] {
            check_size(
                "the film's per-pixel sums",
                sums_bytes,
                limit.0,
                limit.1,
                "render a smaller rectangle",
            )?;
        }
        let mut out_guard = self
            .outputs
            .lock()
            .map_err(|_| GpuError::Device("output cache poisoned".into()))?;
        if out_guard
            .as_ref()
            .is_none_or(|o| o.sum_words < pixels * stride)
        {
            *out_guard = Some(self.create_outputs(pixels * stride));
        }
        let out = out_guard.as_ref().expect("just set");
        let bind_group = self.scene_bind_group(scene, out, sums_bytes, &grid);

        // Adaptive renders run on the stack kernel (as Whitted's distributed
        // effects do).
        let wave = match scene.wave.as_ref().filter(|_| grid.mask.is_none()) {
            Some(p) => Some((p, self.wave_queues(p, &limits)?)),
            None => None,
        };
        let wave_groups = wave
            .as_ref()
            .map(|(_, w)| self.wave_groups(w.as_ref().expect("just set")));
        // Each wavefront dispatch's primary tasks must fit a queue, and a
        // queue's tasks one indirect dispatch.
        let budget = match &wave {
            Some((p, _)) => budget.min(p.queue_cap / 2).max(1),
            None => budget,
        };
        let grid_rect = grid.rect();
        let options = GpuOptions {
            dispatch_pixel_samples: budget,
            ..self.options
        };
        // A listed grid (each block its own range) goes in slices of its
        // items; any other over the round's samples. An error-optimal
        // render's rounds are planned on the GPU (`converge.rs`).
        let rmse = match readout {
            Readout::Rmse(r) => Some(r),
            _ => None,
        };
        let plans: Vec<_> = match (rmse, grid.items()) {
            (Some(_), _) => Vec::new(),
            (None, Some(items)) => vec![plan_listed(
                grid_rect,
                (rect.width, rect.height),
                items,
                frame,
                options,
            )],
            (None, None) => rounds
                .iter()
                .map(|&round| plan(grid_rect, (rect.width, rect.height), round, frame, options))
                .collect(),
        };
        // Timestamps time the submissions of one range (not a resident
        // render's rounds, which are not waited for one by one).
        let query = (self.timestamps && resident.is_none() && rmse.is_none())
            .then(|| self.timestamp_query((plans[0].len() * 2) as u32));

        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera clear"),
            });
        enc.clear_buffer(&out.sums, 0, Some(sums_bytes));
        enc.clear_buffer(&out.counters, 0, None);
        if let Some((_, w)) = &wave {
            enc.clear_buffer(&w.as_ref().expect("set").state, 0, None);
        }
        let mut dispatches = 0u32;
        let mut submissions = 0u32;
        let trace_start = Instant::now();
        self.queue.submit([enc.finish()]);
        let mut chain = match resident {
            Some(r) => Some(
                self.start_rounds(
                    r,
                    rect,
                    &out.sums,
                    sums_bytes,
                    grid.blocks_buffer
                        .as_ref()
                        .expect("a resident render has a block list"),
                )?,
            ),
            None => None,
        };
        let kernel = match (&wave, &wave_groups) {
            (Some((p, w)), Some(groups)) => Driver::Wave(p, w.as_ref().expect("set"), groups),
            _ => Driver::Stack(match grid.mask {
                Some(_) => scene.adaptive.as_ref().expect("made above"),
                None => &scene.pipeline,
            }),
        };
        let rmse_last = match (rmse, &kernel) {
            (Some(r), Driver::Stack(pipeline)) => Some(self.run_rmse_rounds(
                r,
                &grid,
                out,
                sums_bytes,
                &bind_group,
                pipeline,
                frame,
                options,
                progress,
                (&mut dispatches, &mut submissions),
            )?),
            _ => None,
        };
        let mut round = 0;
        while round < plans.len() {
            if chain.as_ref().is_some_and(|c| c.done) {
                break;
            }
            let groups = &plans[round];
            for (g, group) in groups.iter().enumerate() {
                self.queue
                    .write_buffer(&out.params, 0, &params_bytes(group));
                let mut enc = self
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("tessera trace"),
                    });
                {
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("tessera trace"),
                        timestamp_writes: query.as_ref().map(|q| {
                            wgpu::ComputePassTimestampWrites {
                                query_set: &q.set,
                                beginning_of_pass_write_index: Some(2 * g as u32),
                                end_of_pass_write_index: Some(2 * g as u32 + 1),
                            }
                        }),
                    });
                    dispatches += self.encode_group(
                        &mut pass,
                        group,
                        &bind_group,
                        &kernel,
                        scene.data.max_depth,
                    );
                }
                let index = self.queue.submit([enc.finish()]);
                submissions += 1;
                // A resident render's rounds run back to back; its progress
                // comes with each round's report.
                if chain.is_none() {
                    self.wait(index)?;
                    progress(group.iter().map(|d| grid.work(d)).sum());
                }
            }
            if let Some(c) = chain.as_mut() {
                self.end_round(c, round, progress)?;
            }
            round += 1;
        }
        if let Some(c) = chain.as_mut() {
            self.finish_rounds(c, progress)?;
        }
        let trace_wall = trace_start.elapsed();
        let readback_start = Instant::now();

        let rendered = self.read_back(
            readout,
            out,
            sums_bytes,
            samples.len(),
            &grid,
            chain
                .as_ref()
                .map(|c| c.last.as_slice())
                .or(rmse_last.as_deref()),
            wave.as_ref().map(|(_, w)| w.as_ref().expect("set")),
            query.as_ref(),
        )?;
        let Some(rendered) = rendered else {
            return Ok(None);
        };
        let gpu_time = match &query {
            Some(q) => Some(self.gpu_time(q)?),
            None => None,
        };
        let readback = readback_start.elapsed();
        if let Ok(mut s) = self.stats.lock() {
            *s = GpuStats {
                gpu_time,
                trace_wall,
                total_wall: start.elapsed(),
                dispatches,
                submissions,
                overflow_retries: 0,
                readback,
                scene_bytes: scene.data.device_bytes(),
            };
        }
        Ok(Some(rendered))
    }

    /// The read-back after a render's dispatches: its sums into a film
    /// (counts from `grid`; a resident render's blocks at the samples they
    /// `stopped` at), or the image resolved on the GPU, or the sums packed;
    /// the ray counters; the wavefront's overflow flag (`None`: overflowed)
    /// and the timestamps. Every pixel has `samples` samples but where the
    /// grid says otherwise.
    #[allow(clippy::too_many_arguments)]
    fn read_back(
        &self,
        readout: Readout<'_>,
        out: &Outputs,
        sums_bytes: u64,
        samples: u32,
        grid: &Grid<'_>,
        stopped: Option<&[GpuBlockStats]>,
        wave: Option<&WaveBuffers>,
        query: Option<&Timestamps>,
    ) -> Result<Option<Rendered>, GpuError> {
        let rect = grid.film;
        let pixels = rect.area();
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera read-back"),
            });
        let (resolver, packer) = match readout {
            Readout::Sums
            | Readout::Adaptive(_)
            | Readout::Resident(_)
            | Readout::Ranged(..)
            | Readout::Rmse(_) => {
                enc.copy_buffer_to_buffer(&out.sums, 0, &out.sums_read, 0, Some(sums_bytes));
                (None, None)
            }
            Readout::Image(to) => (
                Some((
                    to,
                    self.encode_resolve(&mut enc, &out.sums, sums_bytes, pixels, to, samples)?,
                )),
                None,
            ),
            Readout::Packed => (
                None,
                Some(self.encode_pack(&mut enc, &out.sums, sums_bytes, pixels)?),
            ),
        };
        enc.copy_buffer_to_buffer(&out.counters, 0, &out.counters_read, 0, None);
        // A ranged round's rays per block: the film's runs.
        let rays_read = match (readout, &grid.rays_buffer) {
            (Readout::Ranged(..), Some(b)) => {
                let read = self.buffer(
                    "block rays read",
                    b.size(),
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                );
                enc.copy_buffer_to_buffer(b, 0, &read, 0, None);
                Some(read)
            }
            _ => None,
        };
        if let Some(w) = wave {
            enc.copy_buffer_to_buffer(&w.state, 0, &w.state_read, 0, None);
        }
        if let Some(q) = query {
            enc.resolve_query_set(&q.set, 0..q.count, &q.resolve, 0);
            enc.copy_buffer_to_buffer(&q.resolve, 0, &q.read, 0, None);
        }
        let index = self.queue.submit([enc.finish()]);
        self.wait(index)?;

        if let Some(w) = wave {
            let state: Vec<u32> = self.read(&w.state_read, layout::WAVE_STATE_BYTES)?;
            if state[2] != 0 {
                return Ok(None);
            }
        }
        let counters: Vec<u32> = self.read(&out.counters_read, (COUNTERS * 8) as u64)?;
        let counter = |k: usize| counters[2 * k] as u64 | (counters[2 * k + 1] as u64) << 32;
        let rays = RayCounts {
            primary: counter(layout::COUNTER_PRIMARY),
            shadow: counter(layout::COUNTER_SHADOW),
            reflection: counter(layout::COUNTER_REFLECTION),
            refraction: counter(layout::COUNTER_REFRACTION),
        };
        let nonfinite = counter(layout::COUNTER_NONFINITE);
        let rendered = match (&resolver, &packer) {
            (_, Some(p)) => {
                let (sum_bytes, sums) =
                    self.read_packed(p.as_ref().expect("made by encode_pack"), pixels)?;
                Rendered::Packed(PackedSums {
                    rect,
                    samples,
                    sum_bytes,
                    sums,
                    rays,
                    nonfinite,
                })
            }
            (Some((to, r)), _) => {
                let r = r.as_ref().expect("made by encode_resolve");
                let bytes = to.image_bytes(pixels);
                match to {
                    Resolve::Srgb8 => Rendered::Srgb8(Srgb8Image {
                        rect,
                        rgb: self.read_with(&r.image_read, bytes, |b| b[..pixels * 3].to_vec())?,
                        rays,
                        nonfinite,
                    }),
                    Resolve::Linear => Rendered::Linear(LinearImage {
                        rect,
                        rgb: self.read_with(&r.image_read, bytes, |b| linear_pixels(b, pixels))?,
                        rays,
                        nonfinite,
                    }),
                }
            }
            (None, None) => {
                let mut film = self.read_film(&out.sums_read, sums_bytes, grid)?;
                grid.fill_counts(&mut film, samples, stopped);
                film.rays = rays;
                film.nonfinite = nonfinite;
                if let Some(read) = &rays_read {
                    let words: Vec<u32> = self.read(read, read.size())?;
                    film.runs = grid.runs(&words);
                }
                Rendered::Film(film)
            }
        };
        drop(resolver);
        drop(packer);
        Ok(Some(rendered))
    }

    /// The scene kernel's group 0 for one render.
    fn scene_bind_group(
        &self,
        scene: &SceneState,
        out: &Outputs,
        sums_bytes: u64,
        grid: &Grid<'_>,
    ) -> wgpu::BindGroup {
        let b = |name| wgsl::SCENE.binding(name);
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera render"),
            layout: &self.layout,
            entries: &[
                entire(b("frame"), &scene.frame),
                sized(b("params"), &out.params, size_of::<DispatchParams>() as u64),
                entire(b("spheres"), &scene.spheres),
                entire(b("planes"), &scene.planes),
                entire(b("materials"), &scene.materials),
                entire(b("lights"), &scene.lights),
                sized(b("sums"), &out.sums, sums_bytes),
                entire(b("counters"), &out.counters),
                entire(b("nodes"), &scene.tree[0]),
                entire(b("prims"), &scene.tree[1]),
                entire(b("triangles"), &scene.tree[2]),
                entire(b("shading"), &scene.tree[3]),
                entire(b("instances"), &scene.tree[4]),
                entire(b("dist"), &scene.dist),
                entire(
                    b("active_blocks"),
                    grid.blocks_buffer.as_ref().unwrap_or(&self.no_blocks),
                ),
                entire(
                    b("block_ranges"),
                    grid.ranges_buffer.as_ref().unwrap_or(&self.no_blocks),
                ),
                entire(
                    b("block_rays"),
                    grid.rays_buffer.as_ref().unwrap_or(&self.no_rays),
                ),
                entire(b("mat_pbr"), &scene.pbr[0]),
                entire(b("pbrs"), &scene.pbr[1]),
                entire(b("tri_attrs"), &scene.pbr[2]),
                entire(b("vertex_attrs"), &scene.pbr[3]),
                entire(b("texels"), &scene.pbr[4]),
            ],
        })
    }

    /// The wavefront's queues, grown to `p`'s capacity.
    fn wave_queues(
        &self,
        p: &WavePipelines,
        limits: &wgpu::Limits,
    ) -> Result<std::sync::MutexGuard<'_, Option<WaveBuffers>>, GpuError> {
        let mut guard = self
            .wave
            .lock()
            .map_err(|_| GpuError::Device("wavefront cache poisoned".into()))?;
        let bytes = p.queue_cap * p.task_bytes;
        if guard.as_ref().is_none_or(|w| w.queue_bytes < bytes) {
            check_size(
                "a wavefront task queue",
                bytes,
                limits.max_storage_buffer_binding_size,
                "max_storage_buffer_binding_size",
                "render with --backend cpu",
            )?;
            *guard = Some(self.create_wave_buffers(bytes));
        }
        Ok(guard)
    }

    /// The wavefront's group 1 both ways: primary tasks go to A
    /// (B -> A), then generations alternate A -> B, B -> A.
    fn wave_groups(&self, w: &WaveBuffers) -> (wgpu::BindGroup, wgpu::BindGroup) {
        let q = |name| wgsl::WAVE_QUEUES.binding(name);
        let group = |inq: &wgpu::Buffer, outq: &wgpu::Buffer| {
            self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("tessera wavefront queues"),
                layout: &self.wave_layout,
                entries: &[
                    entire(q("queue_in"), inq),
                    entire(q("queue_out"), outq),
                    entire(q("wave"), &w.state),
                ],
            })
        };
        (group(&w.b, &w.a), group(&w.a, &w.b))
    }

    /// Records one submission's dispatches (`group`, each at its slot of
    /// the params buffer); returns how many dispatches that made.
    fn encode_group(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        group: &[DispatchParams],
        bind_group: &wgpu::BindGroup,
        kernel: &Driver<'_>,
        max_depth: u32,
    ) -> u32 {
        let (wx, wy) = self.options.workgroup;
        let mut dispatches = 0;
        match kernel {
            Driver::Wave(p, w, (to_a, a_to_b)) => {
                for (i, d) in group.iter().enumerate() {
                    pass.set_bind_group(0, bind_group, &[(i as u64 * PARAMS_STRIDE) as u32]);
                    pass.set_bind_group(1, to_a, &[]);
                    pass.set_bind_group(2, &w.args_group, &[]);
                    let n = d.rect_w * d.rows * (d.sample_end - d.sample_start);
                    pass.set_pipeline(&p.primary);
                    pass.dispatch_workgroups(n.div_ceil(wx * wy), 1, 1);
                    // Generation g reads the queue generation g-1 wrote.
                    for g in 0..=max_depth {
                        pass.set_pipeline(&p.swap);
                        pass.dispatch_workgroups(1, 1, 1);
                        pass.set_bind_group(1, if g % 2 == 0 { a_to_b } else { to_a }, &[]);
                        pass.set_pipeline(&p.shade);
                        pass.dispatch_workgroups_indirect(&w.args, 0);
                        dispatches += 2;
                    }
                    dispatches += 1;
                }
            }
            Driver::Stack(pipeline) => {
                pass.set_pipeline(pipeline);
                for (i, d) in group.iter().enumerate() {
                    pass.set_bind_group(0, bind_group, &[(i as u64 * PARAMS_STRIDE) as u32]);
                    if d.ranged != 0 {
                        // 64 invocations a listed item.
                        let (x, y) = listed_groups(d.sample_end - d.sample_start, wx * wy);
                        pass.dispatch_workgroups(x, y, 1);
                    } else {
                        // One invocation per pixel-sample.
                        pass.dispatch_workgroups(
                            d.rect_w.div_ceil(wx),
                            d.rows.div_ceil(wy),
                            d.sample_end - d.sample_start,
                        );
                    }
                    dispatches += 1;
                }
            }
        }
        dispatches
    }

    /// A film of `grid`'s rect from its read-back sums (and squares, in an
    /// adaptive render), straight from the mapped buffer; counts unset.
    fn read_film(
        &self,
        sums_read: &wgpu::Buffer,
        sums_bytes: u64,
        grid: &Grid<'_>,
    ) -> Result<Film, GpuError> {
        let stride = grid.sum_words();
        let mut film = match grid.mask {
            Some(_) => Film::with_squares(grid.film),
            None => Film::new(grid.film),
        };
        self.read_with(sums_read, sums_bytes, |bytes| {
            let words: &[u32] = bytemuck::cast_slice(bytes);
            for (px, w) in film.sums.iter_mut().zip(words.chunks_exact(stride)) {
                for c in 0..3 {
                    px[c] = w[2 * c] as u64 | (w[2 * c + 1] as u64) << 32;
                }
            }
            if let Some(squares) = film.squares.as_mut() {
                for (px, w) in squares.iter_mut().zip(words.chunks_exact(stride)) {
                    for c in 0..3 {
                        let q = &w[SUM_WORDS + 4 * c..SUM_WORDS + 4 * c + 4];
                        px[c] = q.iter().rev().fold(0u128, |acc, &x| acc << 32 | x as u128);
                    }
                }
            }
        })?;
        Ok(film)
    }

    fn timestamp_query(&self, count: u32) -> Timestamps {
        Timestamps {
            set: self.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("tessera timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count,
            }),
            resolve: self.buffer(
                "timestamps",
                count as u64 * 8,
                wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            ),
            read: self.buffer(
                "timestamps read",
                count as u64 * 8,
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ),
            count,
        }
    }

    /// The GPU time between each pass's begin and end timestamps, summed.
    fn gpu_time(&self, q: &Timestamps) -> Result<Duration, GpuError> {
        let ticks: Vec<u64> = self.read(&q.read, q.count as u64 * 8)?;
        let period = self.queue.get_timestamp_period() as f64;
        let ns: f64 = ticks
            .chunks_exact(2)
            .map(|p| p[1].saturating_sub(p[0]) as f64 * period)
            .sum();
        Ok(Duration::from_nanos(ns as u64))
    }

    pub(super) fn create_outputs(&self, sum_words: usize) -> Outputs {
        let sums_bytes = (sum_words * 4) as u64;
        let counters_bytes = (COUNTERS * 8) as u64;
        use wgpu::BufferUsages as U;
        Outputs {
            sum_words,
            sums: self.buffer("sums", sums_bytes, U::STORAGE | U::COPY_SRC | U::COPY_DST),
            sums_read: self.buffer("sums read", sums_bytes, U::MAP_READ | U::COPY_DST),
            counters: self.buffer(
                "counters",
                counters_bytes,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            ),
            counters_read: self.buffer("counters read", counters_bytes, U::MAP_READ | U::COPY_DST),
            params: self.buffer(
                "dispatch params",
                PARAMS_STRIDE * PARAMS_SLOTS as u64,
                U::UNIFORM | U::COPY_DST,
            ),
        }
    }

    pub(super) fn create_wave_buffers(&self, queue_bytes: u64) -> WaveBuffers {
        use wgpu::BufferUsages as U;
        let args = self.buffer(
            "wavefront args",
            layout::WAVE_ARGS_BYTES,
            U::STORAGE | U::INDIRECT,
        );
        let args_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera wavefront args"),
            layout: &self.wave_args_layout,
            entries: &[entire(wgsl::WAVE_ARGS.binding("wave_args_out"), &args)],
        });
        WaveBuffers {
            queue_bytes,
            a: self.buffer("wavefront queue a", queue_bytes, U::STORAGE),
            b: self.buffer("wavefront queue b", queue_bytes, U::STORAGE),
            state: self.buffer(
                "wavefront state",
                layout::WAVE_STATE_BYTES,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            ),
            state_read: self.buffer(
                "wavefront state read",
                layout::WAVE_STATE_BYTES,
                U::MAP_READ | U::COPY_DST,
            ),
            args,
            args_group,
        }
    }
}
