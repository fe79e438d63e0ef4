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

use std::cell::RefCell;
use std::time::Instant;

use wgpu::util::DeviceExt as _;

use super::grid::Grid;
use super::layout::{ConvergeParams, GpuBlockStats};
use super::{GpuError, GpuRenderer, entire, sized, wgsl};
use crate::adaptive::optimal::BlockStats;
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
/// frame and the mode's decisions, taken on the host from the blocks'
/// statistics after each round.
pub(super) struct RmseResident<'a> {
    pub mask: BlockMask,
    pub rounds: RefCell<RmseRounds<'a>>,
}

/// An error-optimal render's rounds in flight.
pub(super) struct RmseChain<'a> {
    resident: &'a RmseResident<'a>,
    group: wgpu::BindGroup,
    _params: wgpu::Buffer,
    stats: wgpu::Buffer,
    read: wgpu::Buffer,
    /// The round's range of every block, in the mask's order, and the
    /// convergence kernel's copy (`count_ranges`).
    counts: Vec<[u32; 2]>,
    ranges: wgpu::Buffer,
    /// The latest statistics: each block's samples.
    pub last: Vec<GpuBlockStats>,
}

/// The convergence kernel, made on first use.
pub(super) struct Converger {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
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
            let (layout, pipeline_layout, module) = self.compute_kernel(
                "tessera converge",
                &wgsl::CONVERGE,
                wgsl::converge_module(wgsl::FILES),
            );
            let pipeline = self
                .device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("tessera converge"),
                    layout: Some(&pipeline_layout),
                    module: &module,
                    entry_point: Some("converge"),
                    compilation_options: Default::default(),
                    cache: self.pipeline_cache(),
                });
            *guard = Some(Converger { layout, pipeline });
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
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tessera converge"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&c.pipeline);
            pass.set_bind_group(0, group, &[]);
            self.dispatch_groups(&mut pass, blocks);
        }
        enc.copy_buffer_to_buffer(stats, 0, read, 0, None);
        Ok(self.queue.submit([enc.finish()]))
    }

    /// Sets up the error-optimal rounds of `resident` over the film `rect`
    /// (sums `sums`; `blocks` the grid's list of every block).
    pub(super) fn start_rmse_rounds<'a>(
        &self,
        resident: &'a RmseResident<'a>,
        rect: Rect,
        sums: &wgpu::Buffer,
        sums_bytes: u64,
        blocks: &wgpu::Buffer,
    ) -> Result<RmseChain<'a>, GpuError> {
        let n = resident.mask.active.len();
        // The first round's ranges in the mask's order (the grid lists its
        // blocks longest range first).
        let counts = resident
            .rounds
            .borrow()
            .pending_ranges()
            .unwrap_or_else(|| vec![[0, 0]; n]);
        let ranges = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("count ranges"),
                contents: bytemuck::cast_slice(&counts),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            });
        let params = ConvergeParams {
            film_w: rect.width,
            film_h: rect.height,
            cols: rect.width.div_ceil(BLOCK),
            blocks: n as u32,
            samples: 0,
            ranged: 1,
            absolute: 0.0,
            relative: 0.0,
        };
        let params = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("converge params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            });
        let bytes = (n * size_of::<GpuBlockStats>()) as u64;
        let stats = self.buffer(
            "block stats",
            bytes,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let read = self.buffer(
            "block stats read",
            bytes,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let group = self.converge_group(&params, sums, sums_bytes, blocks, &stats, &ranges)?;
        Ok(RmseChain {
            resident,
            group,
            _params: params,
            stats,
            read,
            counts,
            ranges,
            last: Vec::new(),
        })
    }

    /// After an error-optimal round's dispatches (submitted, taking each
    /// block over its range of `grid`): its statistics, read back (16 bytes
    /// a block), decide the next round on the host ([`RmseRounds`]), whose
    /// ranges then go to the grid. Whether there is a next round.
    pub(super) fn end_rmse_round(
        &self,
        chain: &mut RmseChain<'_>,
        grid: &mut Grid<'_>,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<bool, GpuError> {
        let mask = &chain.resident.mask;
        let n = mask.active.len();
        let index = self.encode_stats(&chain.group, n as u32, &chain.stats, &chain.read)?;
        let bytes = (n * size_of::<GpuBlockStats>()) as u64;
        chain.last = self.read_after(&chain.read, bytes, Some(index), |b| {
            bytemuck::pod_collect_to_vec::<u8, GpuBlockStats>(b)
        })?;
        progress(
            chain
                .counts
                .iter()
                .enumerate()
                .map(|(i, r)| mask.block_rect(i).area() as u64 * (r[1] - r[0]) as u64)
                .sum(),
        );
        let (mut mean_sum, mut pixels) = (0.0f64, 0u64);
        let stats: Vec<BlockStats> = chain
            .last
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let rect = mask.block_rect(i);
                let area = rect.area() as u64;
                mean_sum += f32::from_bits(s.mean_sum) as f64;
                pixels += area;
                BlockStats {
                    rect,
                    n: s.samples,
                    w: f32::from_bits(s.variance_sum) as f64 * s.samples as f64 / (3 * area) as f64,
                    // The GPU measures no cost per block.
                    cost: 1.0,
                }
            })
            .collect();
        let mut rounds = chain.resident.rounds.borrow_mut();
        rounds.after_round(&stats, mean_sum / (3 * pixels.max(1)) as f64);
        let Some(next) = rounds.pending_ranges() else {
            return Ok(false);
        };
        self.queue
            .write_buffer(&chain.ranges, 0, bytemuck::cast_slice(&next));
        grid.set_ranges(&self.queue, &next);
        chain.counts = next;
        Ok(true)
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
        let no_ranges = self.buffer("no ranges", 8, wgpu::BufferUsages::STORAGE);
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
