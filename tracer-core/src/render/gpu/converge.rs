//! An adaptive render whose rounds chain on the GPU (issue 36): after each
//! round's dispatches, converge.wgsl tests every block still active and
//! retires the converged ones in the trace kernel's own block list, so the
//! next round is queued at once, with no read-back of the film and no
//! decision on the host in between. The host reads 16 bytes a block per
//! round ([`GpuBlockStats`]), one round behind the GPU, for progress and
//! the round's summary; the film is read once, at the end.
//!
//! The decisions are the host's (`adaptive::next_active`): the numerator
//! of each variance exactly, in 128-bit integers, then f32 where the host
//! uses f64, so only a block whose error lies within f32 rounding of the
//! target can go the other way.
//!
//! The error-optimal mode chains its rounds the same way
//! ([`GpuRenderer::run_rmse_rounds`]): after each round's listed
//! dispatches, converge.wgsl (ranged) writes each block's statistics and
//! allocate.wgsl takes the host's decision (`RmseSchedule::after_round`)
//! from them, writing the next round's ranges, items and indirect
//! dispatch arguments; the host reads 32 bytes a round ([`RoundLog`]),
//! one round behind, for the reports and to stop queueing.

use std::cell::RefCell;
use std::time::Instant;

use wgpu::util::DeviceExt as _;

use super::grid::Grid;
use super::layout::{AllocateParams, ConvergeParams, DispatchParams, GpuBlockStats, RoundLog};
use super::plan::{LISTED_CHUNK, listed_groups, listed_slice, slice_items};
use super::{
    GpuError, GpuOptions, GpuRenderer, Outputs, PARAMS_SLOTS, PARAMS_STRIDE, entire, params_bytes,
    sized, wgsl,
};
use crate::adaptive::optimal::RmseStep;
use crate::adaptive::{AdaptiveSettings, BLOCK, BlockMask, BlockStatus, summarize_blocks};
use crate::film::{Rect, SampleRange};
use crate::render::adaptive::{RmseRounds, RoundReport};

/// What an adaptive render on the GPU is given: its settings, every block
/// of the frame, and who is told after each round.
pub(super) struct Resident<'a> {
    pub settings: &'a AdaptiveSettings,
    pub mask: BlockMask,
    pub on_round: &'a dyn Fn(&RoundReport),
}

/// What an error-optimal render on the GPU is given: every block of the
/// frame and the mode's rounds (their settings, the first round's ranges,
/// and who is told of each round).
pub(super) struct RmseResident<'a> {
    pub mask: BlockMask,
    pub rounds: RefCell<RmseRounds<'a>>,
}

/// The convergence and allocation kernels, made on first use.
pub(super) struct Converger {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    allocate_layout: wgpu::BindGroupLayout,
    allocate: wgpu::ComputePipeline,
}

/// One render's rounds in flight.
pub(super) struct Rounds<'a> {
    resident: &'a Resident<'a>,
    rounds: Vec<SampleRange>,
    group: wgpu::BindGroup,
    params: wgpu::Buffer,
    stats: wgpu::Buffer,
    /// One read-back buffer a round: round r's is mapped while r + 1 runs.
    reads: Vec<wgpu::Buffer>,
    /// The round submitted last and not yet reported.
    pending: Option<(usize, wgpu::SubmissionIndex)>,
    /// The latest statistics read back.
    pub last: Vec<GpuBlockStats>,
    /// No block is left active: later rounds need not be submitted.
    pub done: bool,
    reported_at: Instant,
}

impl GpuRenderer {
    fn converger(&self) -> Result<std::sync::MutexGuard<'_, Option<Converger>>, GpuError> {
        let mut guard = self
            .converger
            .lock()
            .map_err(|_| GpuError::Device("convergence kernel cache poisoned".into()))?;
        if guard.is_none() {
            let kernel = |label, layout: &wgsl::Layout, module, entry| {
                let (layout, pipeline_layout, module) = self.compute_kernel(label, layout, module);
                let pipeline =
                    self.device
                        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                            label: Some(label),
                            layout: Some(&pipeline_layout),
                            module: &module,
                            entry_point: Some(entry),
                            compilation_options: Default::default(),
                            cache: self.pipeline_cache(),
                        });
                (layout, pipeline)
            };
            let (layout, pipeline) = kernel(
                "tessera converge",
                &wgsl::CONVERGE,
                wgsl::converge_module(wgsl::FILES),
                "converge",
            );
            let (allocate_layout, allocate) = kernel(
                "tessera allocate",
                &wgsl::ALLOCATE,
                wgsl::allocate_module(wgsl::FILES),
                "allocate",
            );
            *guard = Some(Converger {
                layout,
                pipeline,
                allocate_layout,
                allocate,
            });
        }
        Ok(guard)
    }

    fn converge_group(
        &self,
        params: &wgpu::Buffer,
        sums: &wgpu::Buffer,
        sums_bytes: u64,
        blocks: &wgpu::Buffer,
        stats: &wgpu::Buffer,
        ranges: &wgpu::Buffer,
    ) -> Result<wgpu::BindGroup, GpuError> {
        let guard = self.converger()?;
        let c = guard.as_ref().expect("just made");
        let b = |name| wgsl::CONVERGE.binding(name);
        Ok(self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera converge"),
            layout: &c.layout,
            entries: &[
                entire(b("params"), params),
                sized(b("sums"), sums, sums_bytes),
                entire(b("active_blocks"), blocks),
                entire(b("block_stats"), stats),
                entire(b("count_ranges"), ranges),
            ],
        }))
    }

    /// A pass of `pipeline` with `group` over `groups` workgroups (rows of
    /// them past the per-dimension limit).
    fn encode_pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
        groups: u32,
    ) {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, group, &[]);
        self.dispatch_groups(&mut pass, groups);
    }

    /// The convergence kernel over every block of the group's film, then
    /// its statistics copied to `read`; submitted.
    fn encode_stats(
        &self,
        group: &wgpu::BindGroup,
        blocks: u32,
        stats: &wgpu::Buffer,
        read: &wgpu::Buffer,
    ) -> Result<wgpu::SubmissionIndex, GpuError> {
        let guard = self.converger()?;
        let c = guard.as_ref().expect("made at start");
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera converge"),
            });
        self.encode_pass(&mut enc, "tessera converge", &c.pipeline, group, blocks);
        enc.copy_buffer_to_buffer(stats, 0, read, 0, None);
        Ok(self.queue.submit([enc.finish()]))
    }

    /// An error-optimal render's rounds over `grid` (listed: every block of
    /// the film in the mask's order, the first round's ranges), chained on
    /// the GPU: each round its slices' indirect dispatches of the trace
    /// kernel (`pipeline`, group `scene_group`), then converge.wgsl
    /// (ranged) and allocate.wgsl, which write the next round's ranges and
    /// arguments; each round's [`RoundLog`] is read one round behind, for
    /// its report, until one says the render is done. Each block's final
    /// statistics (its samples: the counts the film has).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn run_rmse_rounds(
        &self,
        resident: &RmseResident<'_>,
        grid: &Grid<'_>,
        out: &Outputs,
        sums_bytes: u64,
        scene_group: &wgpu::BindGroup,
        pipeline: &wgpu::ComputePipeline,
        frame: u32,
        options: GpuOptions,
        progress: &(dyn Fn(u64) + Sync),
        (dispatches, submissions): (&mut u32, &mut u32),
    ) -> Result<Vec<GpuBlockStats>, GpuError> {
        let n = resident.mask.active.len();
        let film = grid.film;
        let settings = *resident.rounds.borrow().settings();
        let max_rounds = settings.max_rounds();
        let ranges = grid.ranges_buffer.as_ref().expect("a listed grid");
        let blocks = grid.blocks_buffer.as_ref().expect("a listed grid");
        let first_items = grid.items().expect("a listed grid");
        // A round's items are at most every block's max_samples: that many
        // slices a round, those past its items dispatching nothing.
        let per = slice_items(options);
        let bound = n as u64 * settings.max_samples.div_ceil(LISTED_CHUNK) as u64;
        let slices = bound.div_ceil(per as u64).max(1) as u32;
        let (wx, wy) = self.options.workgroup;
        let args: Vec<u32> = (0..slices)
            .flat_map(|s| {
                let start = s.saturating_mul(per).min(first_items);
                let (x, y) = listed_groups(per.min(first_items - start), wx * wy);
                [x, y, 1]
            })
            .collect();
        let init = |label, contents: &[u8], usage| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage,
                })
        };
        use wgpu::BufferUsages as U;
        let args = init(
            "rmse dispatch args",
            bytemuck::cast_slice(&args),
            U::STORAGE | U::INDIRECT,
        );
        let log_bytes = size_of::<RoundLog>() as u64;
        let log = self.buffer(
            "rmse round log",
            max_rounds as u64 * log_bytes,
            U::STORAGE | U::COPY_SRC,
        );
        let reads =
            [0, 1].map(|_| self.buffer("rmse round read", log_bytes, U::MAP_READ | U::COPY_DST));
        let stats_bytes = (n * size_of::<GpuBlockStats>()) as u64;
        let stats = self.buffer("block stats", stats_bytes, U::STORAGE | U::COPY_SRC);
        let converge_params = ConvergeParams {
            film_w: film.width,
            film_h: film.height,
            cols: film.width.div_ceil(BLOCK),
            blocks: n as u32,
            samples: 0,
            ranged: 1,
            absolute: 0.0,
            relative: 0.0,
        };
        let converge_params = init(
            "converge params",
            bytemuck::bytes_of(&converge_params),
            U::UNIFORM,
        );
        let mut allocate_params = AllocateParams {
            film_w: film.width,
            film_h: film.height,
            cols: film.width.div_ceil(BLOCK),
            blocks: n as u32,
            min_samples: settings.min_samples,
            max_samples: settings.max_samples,
            max_rounds,
            round: 0,
            chunk: LISTED_CHUNK,
            slices,
            slice_items: per,
            group_invocations: wx * wy,
            target_rmse: settings.target_rmse as f32,
            relative_rmse: settings.relative_rmse as f32,
        };
        let allocate_params_buffer = init(
            "allocate params",
            bytemuck::bytes_of(&allocate_params),
            U::UNIFORM | U::COPY_DST,
        );
        let converge_group = self.converge_group(
            &converge_params,
            &out.sums,
            sums_bytes,
            blocks,
            &stats,
            ranges,
        )?;
        let guard = self.converger()?;
        let c = guard.as_ref().expect("made above");
        let a = |name| wgsl::ALLOCATE.binding(name);
        let allocate_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera allocate"),
            layout: &c.allocate_layout,
            entries: &[
                entire(a("params"), &allocate_params_buffer),
                entire(a("block_stats"), &stats),
                entire(a("ranges"), ranges),
                entire(a("dispatch_args"), &args),
                entire(a("round_log"), &log),
                entire(
                    a("block_rays"),
                    grid.rays_buffer.as_ref().expect("a listed grid"),
                ),
            ],
        });

        // The slices' parameters, PARAMS_SLOTS a submission (the dispatch
        // budget bounds each slice; how many have work the GPU decides).
        let rect = grid.rect();
        let slice_params: Vec<DispatchParams> = (0..slices)
            .map(|s| {
                let start = s.saturating_mul(per);
                listed_slice(
                    rect,
                    (film.width, film.height),
                    frame,
                    start,
                    start.saturating_add(per),
                )
            })
            .collect();
        let one_batch = slice_params.len() <= PARAMS_SLOTS;
        if one_batch {
            self.queue
                .write_buffer(&out.params, 0, &params_bytes(&slice_params));
        }
        // A block's count after round r is at most c_r (c_0 = min, c_{r+1}
        // the step from c_r towards max: `step` grows with the count), and
        // a round adds at most its blocks' counts after it: the slices
        // round r may need.
        let mut most = settings.min_samples;
        let mut slices_of = move || {
            let items = n as u64 * most.div_ceil(LISTED_CHUNK) as u64;
            most = settings.step(most, settings.max_samples);
            items.div_ceil(per as u64).clamp(1, slices as u64) as usize
        };

        let mut capacity = Vec::new();
        let mut reported = 0u64;
        let mut pending: Option<(u32, wgpu::SubmissionIndex)> = None;
        let mut done = false;
        let mut round = 0;
        while round < max_rounds && !done {
            allocate_params.round = round;
            self.queue.write_buffer(
                &allocate_params_buffer,
                0,
                bytemuck::bytes_of(&allocate_params),
            );
            let used = slices_of();
            capacity.push(used as u64 * per as u64);
            let batches: Vec<&[DispatchParams]> =
                slice_params[..used].chunks(PARAMS_SLOTS).collect();
            let mut index = None;
            for (k, b) in batches.iter().enumerate() {
                if !one_batch {
                    self.queue.write_buffer(&out.params, 0, &params_bytes(b));
                }
                let mut enc = self
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("tessera rmse round"),
                    });
                {
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("tessera trace"),
                        timestamp_writes: None,
                    });
                    pass.set_pipeline(pipeline);
                    for i in 0..b.len() {
                        pass.set_bind_group(0, scene_group, &[(i as u64 * PARAMS_STRIDE) as u32]);
                        let slice = (k * PARAMS_SLOTS + i) as u64;
                        pass.dispatch_workgroups_indirect(&args, slice * 12);
                        *dispatches += 1;
                    }
                }
                if k + 1 == batches.len() {
                    // The round's decision, after its last slice.
                    self.encode_pass(
                        &mut enc,
                        "tessera converge",
                        &c.pipeline,
                        &converge_group,
                        n as u32,
                    );
                    self.encode_pass(
                        &mut enc,
                        "tessera allocate",
                        &c.allocate,
                        &allocate_group,
                        1,
                    );
                    enc.copy_buffer_to_buffer(
                        &log,
                        round as u64 * log_bytes,
                        &reads[round as usize % 2],
                        0,
                        log_bytes,
                    );
                }
                index = Some(self.queue.submit([enc.finish()]));
                *submissions += 1;
            }
            let index = index.expect("a batch at least");
            if let Some(before) = pending.replace((round, index)) {
                let next =
                    self.report_rmse_round(resident, &reads, before, &mut reported, progress)?;
                // The round queued after it must have held its items.
                if next as u64 > capacity[round as usize] {
                    return Err(GpuError::Device(format!(
                        "error-optimal round {round} has {next} items, over the {} its dispatches cover",
                        capacity[round as usize]
                    )));
                }
                done = next == 0;
            }
            round += 1;
        }
        if let Some(last) = pending.take()
            && !done
        {
            self.report_rmse_round(resident, &reads, last, &mut reported, progress)?;
        }
        drop(guard);
        // The blocks' final counts, from the last statistics.
        let read = self.buffer("block stats read", stats_bytes, U::MAP_READ | U::COPY_DST);
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera rmse counts"),
            });
        enc.copy_buffer_to_buffer(&stats, 0, &read, 0, stats_bytes);
        let index = self.queue.submit([enc.finish()]);
        self.read_after(&read, stats_bytes, Some(index), |b| {
            bytemuck::pod_collect_to_vec::<u8, GpuBlockStats>(b)
        })
    }

    /// Reads round `round`'s log (its submission `index`), reports it and
    /// its pixel-samples; the next round's items (0: the render is done).
    fn report_rmse_round(
        &self,
        resident: &RmseResident<'_>,
        reads: &[wgpu::Buffer; 2],
        (round, index): (u32, wgpu::SubmissionIndex),
        reported: &mut u64,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<u32, GpuError> {
        let log = self.read_after(
            &reads[round as usize % 2],
            size_of::<RoundLog>() as u64,
            Some(index),
            bytemuck::pod_read_unaligned::<RoundLog>,
        )?;
        let pixel_samples = log.samples[0] as u64 | (log.samples[1] as u64) << 32;
        progress(pixel_samples.saturating_sub(*reported));
        *reported = pixel_samples;
        resident.rounds.borrow_mut().report(&RmseStep {
            round,
            active_blocks: log.active_blocks as usize,
            pixel_samples,
            estimated_rmse: (log.estimated_mse as f64).sqrt(),
            target_rmse: (log.target_mse as f64).sqrt(),
            expected_pixel_samples: (log.expected_samples as f64).max(pixel_samples as f64) as u64,
        });
        Ok(log.next_items)
    }

    /// Sets up the rounds of `resident` over the film `rect` whose sums are
    /// `sums` and whose block list (every block, in mask order) is `blocks`.
    pub(super) fn start_rounds<'a>(
        &self,
        resident: &'a Resident<'a>,
        rect: Rect,
        sums: &wgpu::Buffer,
        sums_bytes: u64,
        blocks: &wgpu::Buffer,
    ) -> Result<Rounds<'a>, GpuError> {
        let n = resident.mask.active.len();
        let rounds = resident.settings.rounds();
        let target = resident.settings.target();
        let params = ConvergeParams {
            film_w: rect.width,
            film_h: rect.height,
            cols: rect.width.div_ceil(BLOCK),
            blocks: n as u32,
            samples: 0,
            ranged: 0,
            absolute: target.absolute as f32,
            relative: target.relative as f32,
        };
        let params = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("converge params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            });
        let bytes = (n * size_of::<GpuBlockStats>()) as u64;
        let stats = self.buffer(
            "block stats",
            bytes,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let reads = (0..rounds.len())
            .map(|_| {
                self.buffer(
                    "block stats read",
                    bytes,
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                )
            })
            .collect();
        // The per-pixel test reads no ranges: a stand-in binding.
        let no_ranges = self.buffer("no ranges", 16, wgpu::BufferUsages::STORAGE);
        let group = self.converge_group(&params, sums, sums_bytes, blocks, &stats, &no_ranges)?;
        Ok(Rounds {
            resident,
            rounds,
            group,
            params,
            stats,
            reads,
            pending: None,
            last: vec![GpuBlockStats::default(); n],
            done: false,
            reported_at: Instant::now(),
        })
    }

    /// Queues the convergence test after round `round`'s dispatches (already
    /// submitted), then reports the round before it, which by then is done
    /// or nearly (the GPU goes on with this one meanwhile).
    pub(super) fn end_round(
        &self,
        rounds: &mut Rounds<'_>,
        round: usize,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<(), GpuError> {
        let samples = rounds.rounds[round].end;
        // `samples` is the 5th word of ConvergeParams.
        self.queue
            .write_buffer(&rounds.params, 16, bytemuck::bytes_of(&samples));
        let index = self.encode_stats(
            &rounds.group,
            rounds.last.len() as u32,
            &rounds.stats,
            &rounds.reads[round],
        )?;
        if let Some(before) = rounds.pending.replace((round, index)) {
            self.report_round(rounds, before, progress)?;
        }
        Ok(())
    }

    /// Reports the last round submitted; its statistics are then
    /// `rounds.last`.
    pub(super) fn finish_rounds(
        &self,
        rounds: &mut Rounds<'_>,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<(), GpuError> {
        if let Some(last) = rounds.pending.take() {
            self.report_round(rounds, last, progress)?;
        }
        Ok(())
    }

    fn report_round(
        &self,
        rounds: &mut Rounds<'_>,
        (round, index): (usize, wgpu::SubmissionIndex),
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<(), GpuError> {
        // read_after waits for the round's submission, and no later one.
        let read = &rounds.reads[round];
        let bytes = (rounds.last.len() * size_of::<GpuBlockStats>()) as u64;
        rounds.last = self.read_after(read, bytes, Some(index), |b| {
            bytemuck::pod_collect_to_vec::<u8, GpuBlockStats>(b)
        })?;
        let range = rounds.rounds[round];
        let mask = &rounds.resident.mask;
        let a = rounds.resident.settings;
        let (mut active, mut pixels, mut going_on) = (0usize, 0u64, 0usize);
        let errors: Vec<BlockStatus> = rounds
            .last
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let area = mask.block_rect(i).area() as u64;
                let worst = f32::from_bits(s.worst) as f64;
                let e = BlockStatus {
                    area,
                    samples: s.samples,
                    variance_sum: f32::from_bits(s.variance_sum) as f64,
                    worst: if worst >= 3.0e38 {
                        f64::INFINITY
                    } else {
                        worst
                    },
                };
                if s.samples == range.end {
                    active += 1;
                    pixels += area;
                    going_on += usize::from(e.worst > 1.0);
                }
                e
            })
            .collect();
        rounds.done = going_on == 0 || range.end >= a.max_samples;
        if active == 0 {
            // A round queued before the one ahead of it retired every
            // block: it traced nothing, and the host's driver would not
            // have run it.
            return Ok(());
        }
        progress(pixels * range.len() as u64);
        let now = Instant::now();
        (rounds.resident.on_round)(&RoundReport {
            round,
            samples: range,
            active_blocks: active,
            seconds: (now - rounds.reported_at).as_secs_f64(),
            summary: summarize_blocks(errors, a),
        });
        rounds.reported_at = now;
        Ok(())
    }
}
