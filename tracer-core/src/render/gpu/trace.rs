//! One render on the GPU: clear, the planned dispatches in bounded
//! submissions (the stack kernel, or the wavefront's generations), and the
//! read-back of sums and counters into a film (or the resolved image).

use std::time::{Duration, Instant};

use wgpu::util::DeviceExt as _;

use super::layout::{self, ADAPTIVE_SUM_WORDS, COUNTERS, DispatchParams, SUM_WORDS, SceneData};
use super::plan::plan;
use super::readback::linear_pixels;
use super::wgsl;
use super::{
    GpuError, GpuOptions, GpuRenderer, GpuStats, LinearImage, Outputs, PARAMS_SLOTS, PARAMS_STRIDE,
    PackedSums, Readout, Rendered, Resolve, Srgb8Image, WaveBuffers, check_size, entire,
};
use crate::adaptive::BLOCK;
use crate::film::{Film, RayCounts, Rect, SampleRange};

impl GpuRenderer {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn render_inner(
        &self,
        data: SceneData,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
        start: Instant,
        budget: u64,
        readout: Readout<'_>,
    ) -> Result<Option<Rendered>, GpuError> {
        let limits = self.device.limits();
        let mut scene_guard = self
            .scene
            .lock()
            .map_err(|_| GpuError::Device("scene cache poisoned".into()))?;
        if scene_guard
            .as_ref()
            .is_none_or(|s| s.data != data || s.options != self.options)
        {
            let old = scene_guard.take();
            *scene_guard = Some(self.upload_scene(data, &limits, old)?);
        }
        let mask = match readout {
            Readout::Adaptive(m) => Some(m),
            Readout::Resident(r) => Some(&r.mask),
            Readout::Ranged(m, _) => Some(m),
            _ => None,
        };
        // A ranged render's (first, end) per listed block.
        let ranges = match readout {
            Readout::Ranged(m, r) => Some(
                m.active
                    .iter()
                    .zip(r)
                    .filter(|(a, _)| **a)
                    .map(|(_, &(a, b))| [a, b])
                    .collect::<Vec<[u32; 2]>>(),
            ),
            _ => None,
        };
        let resident = match readout {
            Readout::Resident(r) => Some(r),
            _ => None,
        };
        // A resident adaptive render runs all its rounds here; any other
        // render is one range of samples.
        let rounds = resident.map_or_else(|| vec![samples], |r| r.settings.rounds());
        if mask.is_some() {
            let scene = scene_guard.as_mut().expect("just set");
            if scene.adaptive.is_none() {
                scene.adaptive = Some(self.adaptive_pipeline(scene));
            }
        }
        let scene = scene_guard.as_ref().expect("just set");

        let pixels = rect.area();
        let stride = if mask.is_some() {
            ADAPTIVE_SUM_WORDS
        } else {
            SUM_WORDS
        };
        let sums_bytes = (pixels * stride * 4) as u64;
        check_size(
            "the film's per-pixel sums",
            sums_bytes,
            limits.max_storage_buffer_binding_size,
            "max_storage_buffer_binding_size",
        )?;
        check_size(
            "the film's per-pixel sums",
            sums_bytes,
            limits.max_buffer_size,
            "max_buffer_size",
        )?;
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
        // An adaptive round's grid: 8 columns, 8 rows per active block
        // (sums.wgsl grid_pixel), its blocks listed as column | row << 16.
        let blocks: Vec<u32> = mask.map_or_else(Vec::new, |m| {
            let cols = m.cols() as usize;
            m.active
                .iter()
                .enumerate()
                .filter(|(_, a)| **a)
                .map(|(i, _)| (i % cols) as u32 | ((i / cols) as u32) << 16)
                .collect()
        });
        let ranges_buffer = ranges.as_ref().map(|r| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("block ranges"),
                    contents: bytemuck::cast_slice(r),
                    usage: wgpu::BufferUsages::STORAGE,
                })
        });
        let blocks_buffer = mask.map(|_| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("active blocks"),
                    contents: bytemuck::cast_slice(&blocks),
                    usage: wgpu::BufferUsages::STORAGE,
                })
        });
        let grid = match mask {
            Some(_) => Rect::new(rect.x, rect.y, BLOCK, BLOCK * blocks.len() as u32),
            None => rect,
        };
        // Pixel-samples a dispatch traces: the film's pixels in its band of
        // the grid's rows (blocks cut by the film's edge hold fewer than
        // their 64 grid cells) times its samples (in a ranged render, those
        // of each block's range).
        let dispatch_work = |d: &DispatchParams| -> u64 {
            let n = (d.sample_end - d.sample_start) as u64;
            match mask {
                None => rect.width as u64 * d.rows as u64 * n,
                Some(_) => (d.row0..d.row0 + d.rows)
                    .map(|r| {
                        let b = blocks[(r / BLOCK) as usize];
                        let (fx, fy) = ((b & 0xffff) * BLOCK, (b >> 16) * BLOCK + r % BLOCK);
                        let samples = match &ranges {
                            Some(rs) => {
                                let [a, e] = rs[(r / BLOCK) as usize];
                                d.sample_end.min(e - a).saturating_sub(d.sample_start) as u64
                            }
                            None => n,
                        };
                        if fy < rect.height {
                            (rect.width - fx).min(BLOCK) as u64 * samples
                        } else {
                            0
                        }
                    })
                    .sum(),
            }
        };

        let b = |name| wgsl::SCENE.binding(name);
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera render"),
            layout: &self.layout,
            entries: &[
                entire(b("frame"), &scene.frame),
                wgpu::BindGroupEntry {
                    binding: b("params"),
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &out.params,
                        offset: 0,
                        size: wgpu::BufferSize::new(size_of::<DispatchParams>() as u64),
                    }),
                },
                entire(b("spheres"), &scene.spheres),
                entire(b("planes"), &scene.planes),
                entire(b("materials"), &scene.materials),
                entire(b("lights"), &scene.lights),
                wgpu::BindGroupEntry {
                    binding: b("sums"),
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &out.sums,
                        offset: 0,
                        size: wgpu::BufferSize::new(sums_bytes),
                    }),
                },
                entire(b("counters"), &out.counters),
                entire(b("nodes"), &scene.tree[0]),
                entire(b("prims"), &scene.tree[1]),
                entire(b("triangles"), &scene.tree[2]),
                entire(b("shading"), &scene.tree[3]),
                entire(b("dist"), &scene.dist),
                entire(
                    b("active_blocks"),
                    blocks_buffer.as_ref().unwrap_or(&self.no_blocks),
                ),
                entire(
                    b("block_ranges"),
                    ranges_buffer.as_ref().unwrap_or(&self.no_blocks),
                ),
                entire(b("mat_pbr"), &scene.pbr[0]),
                entire(b("pbrs"), &scene.pbr[1]),
                entire(b("tri_attrs"), &scene.pbr[2]),
                entire(b("vertex_attrs"), &scene.pbr[3]),
                entire(b("texels"), &scene.pbr[4]),
            ],
        });

        let (wx, wy) = self.options.workgroup;
        // Adaptive rounds run on the stack kernel (as distributed effects do).
        let wave = match scene.wave.as_ref().filter(|_| mask.is_none()) {
            Some(p) => {
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
                    )?;
                    *guard = Some(self.create_wave_buffers(bytes));
                }
                Some((p, guard))
            }
            None => None,
        };
        let wave_groups = wave.as_ref().map(|(_, w)| {
            let w = w.as_ref().expect("just set");
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
            // Primary tasks go to A; generations then alternate A->B, B->A.
            (group(&w.b, &w.a), group(&w.a, &w.b))
        });
        // Each wavefront dispatch's primary tasks must fit a queue, and a
        // queue's tasks one indirect dispatch.
        let budget = match &wave {
            Some((p, _)) => budget.min(p.queue_cap / 2).max(1),
            None => budget,
        };
        let plans: Vec<_> = rounds
            .iter()
            .map(|&round| {
                let mut groups = plan(
                    grid,
                    (rect.width, rect.height),
                    round,
                    frame,
                    GpuOptions {
                        dispatch_pixel_samples: budget,
                        ..self.options
                    },
                );
                if ranges.is_some() {
                    for d in groups.iter_mut().flatten() {
                        d.ranged = 1;
                    }
                }
                groups
            })
            .collect();
        // Timestamps time the submissions of one range (not a resident
        // render's rounds, which are not waited for one by one).
        let query = (self.timestamps && resident.is_none()).then(|| {
            let n = (plans[0].len() * 2) as u32;
            let set = self.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("tessera timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: n,
            });
            let resolve = self.buffer(
                "timestamps",
                n as u64 * 8,
                wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            );
            let read = self.buffer(
                "timestamps read",
                n as u64 * 8,
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            );
            (set, resolve, read, n)
        });

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
                    blocks_buffer
                        .as_ref()
                        .expect("a resident render has a block list"),
                )?,
            ),
            None => None,
        };
        for (round, groups) in plans.iter().enumerate() {
            if chain.as_ref().is_some_and(|c| c.done) {
                break;
            }
            for (g, group) in groups.iter().enumerate() {
                let mut params = vec![0u8; group.len() * PARAMS_STRIDE as usize];
                for (i, d) in group.iter().enumerate() {
                    let at = i * PARAMS_STRIDE as usize;
                    params[at..at + size_of::<DispatchParams>()]
                        .copy_from_slice(bytemuck::bytes_of(d));
                }
                self.queue.write_buffer(&out.params, 0, &params);
                let mut enc = self
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("tessera trace"),
                    });
                {
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("tessera trace"),
                        timestamp_writes: query.as_ref().map(|(set, ..)| {
                            wgpu::ComputePassTimestampWrites {
                                query_set: set,
                                beginning_of_pass_write_index: Some(2 * g as u32),
                                end_of_pass_write_index: Some(2 * g as u32 + 1),
                            }
                        }),
                    });
                    match (&wave, &wave_groups) {
                        (Some((p, w)), Some((to_a, a_to_b))) => {
                            let w = w.as_ref().expect("set");
                            let threads = wx * wy;
                            for (i, d) in group.iter().enumerate() {
                                pass.set_bind_group(
                                    0,
                                    &bind_group,
                                    &[(i as u64 * PARAMS_STRIDE) as u32],
                                );
                                pass.set_bind_group(1, to_a, &[]);
                                pass.set_bind_group(2, &w.args_group, &[]);
                                let n = d.rect_w * d.rows * (d.sample_end - d.sample_start);
                                pass.set_pipeline(&p.primary);
                                pass.dispatch_workgroups(n.div_ceil(threads), 1, 1);
                                // Generation g reads the queue generation g-1 wrote.
                                for g in 0..=scene.data.max_depth {
                                    pass.set_pipeline(&p.swap);
                                    pass.dispatch_workgroups(1, 1, 1);
                                    pass.set_bind_group(
                                        1,
                                        if g % 2 == 0 { a_to_b } else { to_a },
                                        &[],
                                    );
                                    pass.set_pipeline(&p.shade);
                                    pass.dispatch_workgroups_indirect(&w.args, 0);
                                    dispatches += 2;
                                }
                                dispatches += 1;
                            }
                        }
                        _ => {
                            pass.set_pipeline(match mask {
                                Some(_) => scene.adaptive.as_ref().expect("made above"),
                                None => &scene.pipeline,
                            });
                            for (i, d) in group.iter().enumerate() {
                                pass.set_bind_group(
                                    0,
                                    &bind_group,
                                    &[(i as u64 * PARAMS_STRIDE) as u32],
                                );
                                // One invocation per pixel-sample.
                                pass.dispatch_workgroups(
                                    d.rect_w.div_ceil(wx),
                                    d.rows.div_ceil(wy),
                                    d.sample_end - d.sample_start,
                                );
                                dispatches += 1;
                            }
                        }
                    }
                }
                let index = self.queue.submit([enc.finish()]);
                submissions += 1;
                // A resident render's rounds run back to back; its progress
                // comes with each round's report.
                if chain.is_none() {
                    self.wait(index)?;
                    progress(group.iter().map(dispatch_work).sum());
                }
            }
            if let Some(c) = chain.as_mut() {
                self.end_round(c, round, progress)?;
            }
        }
        if let Some(c) = chain.as_mut() {
            self.finish_rounds(c, progress)?;
        }
        let trace_wall = trace_start.elapsed();
        let readback_start = Instant::now();

        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera read-back"),
            });
        let (resolver, packer) = match readout {
            Readout::Sums | Readout::Adaptive(_) | Readout::Resident(_) | Readout::Ranged(..) => {
                enc.copy_buffer_to_buffer(&out.sums, 0, &out.sums_read, 0, Some(sums_bytes));
                (None, None)
            }
            Readout::Image(to) => (
                Some((
                    to,
                    self.encode_resolve(
                        &mut enc,
                        &out.sums,
                        sums_bytes,
                        pixels,
                        to,
                        samples.len(),
                    )?,
                )),
                None,
            ),
            Readout::Packed => (
                None,
                Some(self.encode_pack(&mut enc, &out.sums, sums_bytes, pixels)?),
            ),
        };
        enc.copy_buffer_to_buffer(&out.counters, 0, &out.counters_read, 0, None);
        if let Some((_, w)) = &wave {
            let w = w.as_ref().expect("set");
            enc.copy_buffer_to_buffer(&w.state, 0, &w.state_read, 0, None);
        }
        if let Some((set, resolve, read, n)) = &query {
            enc.resolve_query_set(set, 0..*n, resolve, 0);
            enc.copy_buffer_to_buffer(resolve, 0, read, 0, None);
        }
        let index = self.queue.submit([enc.finish()]);
        self.wait(index)?;

        if let Some((_, w)) = &wave {
            let state: Vec<u32> = self.read(
                &w.as_ref().expect("set").state_read,
                layout::WAVE_STATE_BYTES,
            )?;
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
                    samples: samples.len(),
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
                let mut film = match mask {
                    Some(_) => Film::with_squares(rect),
                    None => Film::new(rect),
                };
                // Straight from the mapped buffer into the film: no intermediate copy.
                self.read_with(&out.sums_read, sums_bytes, |bytes| {
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
                match (mask, &chain) {
                    // Each block at the samples it stopped at.
                    (Some(m), Some(c)) => {
                        for (i, st) in c.last.iter().enumerate() {
                            let b = m.block_rect(i);
                            for y in b.y..b.y + b.height {
                                let row = ((y - rect.y) * rect.width + (b.x - rect.x)) as usize;
                                film.counts[row..row + b.width as usize].fill(st.samples);
                            }
                        }
                    }
                    (Some(m), None) if ranges.is_some() => {
                        if let Readout::Ranged(_, r) = readout {
                            for (i, &(a, e)) in r.iter().enumerate().filter(|(i, _)| m.active[*i]) {
                                let b = m.block_rect(i);
                                for y in b.y..b.y + b.height {
                                    let row = ((y - rect.y) * rect.width + (b.x - rect.x)) as usize;
                                    film.counts[row..row + b.width as usize].fill(e - a);
                                }
                            }
                        }
                    }
                    (Some(m), None) => {
                        for b in m.active_rects() {
                            for y in b.y..b.y + b.height {
                                let row = ((y - rect.y) * rect.width + (b.x - rect.x)) as usize;
                                film.counts[row..row + b.width as usize].fill(samples.len());
                            }
                        }
                    }
                    (None, _) => film.counts.fill(samples.len()),
                }
                film.rays = rays;
                film.nonfinite = nonfinite;
                Rendered::Film(film)
            }
        };
        drop(resolver);
        drop(packer);
        let gpu_time = match &query {
            Some((_, _, read, n)) => {
                let ticks: Vec<u64> = self.read(read, *n as u64 * 8)?;
                let period = self.queue.get_timestamp_period() as f64;
                let ns: f64 = ticks
                    .chunks_exact(2)
                    .map(|p| p[1].saturating_sub(p[0]) as f64 * period)
                    .sum();
                Some(Duration::from_nanos(ns as u64))
            }
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
            };
        }
        Ok(Some(rendered))
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
