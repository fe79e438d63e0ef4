//! The GPU launch-shape sweep: workgroup size x pixel-samples per dispatch,
//! for the stack and the wavefront kernel, timed the same way everywhere.
//!
//! One implementation for two users: `tessera bench launch` (CSV and plot)
//! and `tracer-core/examples/gpu_bench.rs` (markdown tables); it lives here
//! because both reach tracer-core (the example cannot depend on the
//! `tessera` binary crate).

use crate::film::WorkRegion;
use crate::render::{Output, Rendered};
use std::time::{Duration, Instant};

use super::{GpuError, GpuOptions, GpuRenderer, Strategy};
use crate::film::{Film, RayCounts, Rect, SampleRange};
use crate::render::PreparedFrame;

/// Renders before the timed ones: the first builds the pipeline and uploads
/// the scene, the others let clocks ramp up.
pub const WARMUP: usize = 3;

/// Host and GPU times of one renderer on one frame (medians of the timed renders).
pub struct Timing {
    /// The last timed render's image.
    pub film: Film,
    /// Tracing passes from timestamp queries, else `trace`.
    pub gpu: Duration,
    /// Host wall time from the first submission to completion, read-back excluded.
    pub trace: Duration,
    /// The whole render call: upload, tracing, read-back, conversion.
    pub total: Duration,
    pub readback: Duration,
    /// The first render (pipeline build and scene upload included).
    pub first: Duration,
    pub dispatches: u32,
}

/// The timed renders of one renderer.
#[derive(Clone, Default)]
struct Samples {
    gpu: Vec<Duration>,
    trace: Vec<Duration>,
    total: Vec<Duration>,
    readback: Vec<Duration>,
    dispatches: u32,
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

/// Renders `prepared` (whole frame, all `samples`) with several renderers,
/// interleaved render by render so that clock ramps and other drift hit
/// every one alike, after [`WARMUP`] renders each; `reps` timed renders each.
pub fn run_interleaved(
    rs: &[&GpuRenderer],
    prepared: &PreparedFrame,
    rect: Rect,
    samples: u32,
    reps: usize,
) -> Result<Vec<Timing>, GpuError> {
    let samples = SampleRange::all(samples);
    let mut films = vec![];
    let mut firsts = vec![];
    for g in rs {
        let t = Instant::now();
        films.push(g.render(prepared, WorkRegion::new(0, rect, samples), &|_| {})?);
        firsts.push(t.elapsed());
    }
    for _ in 1..WARMUP {
        for g in rs {
            g.render(prepared, WorkRegion::new(0, rect, samples), &|_| {})?;
        }
    }
    let mut stats = vec![Samples::default(); rs.len()];
    for _ in 0..reps.max(1) {
        for (i, g) in rs.iter().enumerate() {
            films[i] = g.render(prepared, WorkRegion::new(0, rect, samples), &|_| {})?;
            let st = g.last_stats();
            let t = &mut stats[i];
            t.gpu.push(st.gpu_time.unwrap_or(st.trace_wall));
            t.trace.push(st.trace_wall);
            t.total.push(st.total_wall);
            t.readback.push(st.readback);
            t.dispatches = st.dispatches;
        }
    }
    Ok(films
        .into_iter()
        .zip(stats)
        .zip(firsts)
        .map(|((film, t), first)| Timing {
            film,
            gpu: median(t.gpu),
            trace: median(t.trace),
            total: median(t.total),
            readback: median(t.readback),
            first,
            dispatches: t.dispatches,
        })
        .collect())
}

/// A local render's ways to its image, interleaved call by call after
/// [`WARMUP`] calls each (medians of `reps`): reading back the sums and
/// resolving on the host (a farm result's path), or resolving on the GPU
/// and reading back only the image (`tessera render --backend gpu`), to
/// 8 bits (PNG) and to f32 (EXR). Also whether each pair gives the same
/// image, bit for bit.
pub struct ReadoutTiming {
    /// The sums alone, read back into a film: what either host resolve starts from.
    pub sums: Duration,
    pub sums_then_host: Duration,
    pub resolved_on_gpu: Duration,
    pub sums_then_host_linear: Duration,
    pub linear_on_gpu: Duration,
    pub identical: bool,
}

pub fn readout_timing(
    g: &GpuRenderer,
    prepared: &PreparedFrame,
    rect: Rect,
    samples: u32,
    reps: usize,
) -> Result<ReadoutTiming, GpuError> {
    let samples = SampleRange::all(samples);
    let sums = || g.render(prepared, WorkRegion::new(0, rect, samples), &|_| {});
    let bits = |v: &[[f32; 3]]| -> Vec<u32> { v.iter().flatten().map(|x| x.to_bits()).collect() };
    let region = WorkRegion::new(0, rect, samples);
    let srgb8_on_gpu = || match g.render_as(prepared, region, Output::Srgb8, &|_| {})? {
        Rendered::Srgb8(i) => Ok::<_, GpuError>(i.rgb),
        _ => unreachable!("asked for the 8-bit image"),
    };
    let linear_on_gpu = || match g.render_as(prepared, region, Output::Linear, &|_| {})? {
        Rendered::Linear(i) => Ok::<_, GpuError>(i.rgb),
        _ => unreachable!("asked for the linear image"),
    };
    let mut identical = true;
    for _ in 0..WARMUP {
        let film = sums()?;
        identical &= film.srgb8() == srgb8_on_gpu()?;
        identical &= bits(&film.resolve()) == bits(&linear_on_gpu()?);
    }
    // Each call timed alone; the images compared after.
    let mut times: [Vec<Duration>; 5] = Default::default();
    for _ in 0..reps.max(1) {
        let t = Instant::now();
        sums()?;
        times[0].push(t.elapsed());
        let t = Instant::now();
        let x = sums()?.srgb8();
        times[1].push(t.elapsed());
        let t = Instant::now();
        let y = srgb8_on_gpu()?;
        times[2].push(t.elapsed());
        identical &= x == y;
        let t = Instant::now();
        let x = sums()?.resolve();
        times[3].push(t.elapsed());
        let t = Instant::now();
        let y = linear_on_gpu()?;
        times[4].push(t.elapsed());
        identical &= bits(&x) == bits(&y);
    }
    let [a, b, c, d, e] = times.map(median);
    Ok(ReadoutTiming {
        sums: a,
        sums_then_host: b,
        resolved_on_gpu: c,
        sums_then_host_linear: d,
        linear_on_gpu: e,
        identical,
    })
}

/// One point of the sweep.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LaunchShape {
    pub strategy: Strategy,
    pub workgroup: (u32, u32),
    pub dispatch_pixel_samples: u64,
}

impl LaunchShape {
    /// The renderer options of this point. A submission holds at least one
    /// dispatch and never less than the default's work, so only the
    /// dispatch size varies.
    pub fn options(&self) -> GpuOptions {
        let d = GpuOptions::default();
        GpuOptions {
            workgroup: self.workgroup,
            dispatch_pixel_samples: self.dispatch_pixel_samples,
            submit_pixel_samples: d.submit_pixel_samples.max(self.dispatch_pixel_samples),
            strategy: self.strategy,
        }
    }

    pub fn strategy_name(&self) -> &'static str {
        strategy_name(self.strategy)
    }
}

pub fn strategy_name(s: Strategy) -> &'static str {
    match s {
        Strategy::Stack => "stack",
        Strategy::Wavefront => "wavefront",
    }
}

/// Pixel-samples per dispatch of the full sweep.
pub const DISPATCH_SIZES: &[u64] = &[1 << 16, 1 << 18, 1 << 20, 1 << 22, 1 << 24];
/// Workgroup shapes of the stack kernel (2-D tiles and 1-D rows).
pub const STACK_WORKGROUPS: &[(u32, u32)] = &[
    (32, 1),
    (64, 1),
    (128, 1),
    (256, 1),
    (8, 4),
    (8, 8),
    (16, 8),
    (16, 16),
    (32, 4),
    (32, 8),
];
/// The wavefront kernel works on 1-D queues.
pub const WAVEFRONT_WORKGROUPS: &[(u32, u32)] = &[(32, 1), (64, 1), (128, 1), (256, 1)];

/// The points to sweep: the full grid, or (quick) a few that still cover
/// both kernels, a 1-D and a 2-D workgroup, and a split and an unsplit frame.
pub fn sweep_shapes(quick: bool) -> Vec<LaunchShape> {
    const QUICK_STACK: &[(u32, u32)] = &[(64, 1), (8, 8)];
    const QUICK_WAVEFRONT: &[(u32, u32)] = &[(64, 1)];
    const QUICK_SIZES: &[u64] = &[1 << 10, 1 << 24];
    let (stack_wg, wave_wg, sizes) = if quick {
        (QUICK_STACK, QUICK_WAVEFRONT, QUICK_SIZES)
    } else {
        (STACK_WORKGROUPS, WAVEFRONT_WORKGROUPS, DISPATCH_SIZES)
    };
    let mut out = vec![];
    for (strategy, wgs) in [(Strategy::Stack, stack_wg), (Strategy::Wavefront, wave_wg)] {
        for &workgroup in wgs {
            for &dispatch_pixel_samples in sizes {
                out.push(LaunchShape {
                    strategy,
                    workgroup,
                    dispatch_pixel_samples,
                });
            }
        }
    }
    out
}

/// A measured point: its times, rays, and how far its image is from the
/// baseline's (the default options), which every shape must reproduce.
pub struct SweepPoint {
    pub shape: LaunchShape,
    /// `Err` when the adapter rejects the shape (e.g. a workgroup over its
    /// limits) or the render fails: the sweep goes on.
    pub result: Result<SweepTiming, String>,
}

pub struct SweepTiming {
    pub gpu: Duration,
    pub trace: Duration,
    pub total: Duration,
    pub readback: Duration,
    /// The first render: pipeline build and scene upload included.
    pub first: Duration,
    pub dispatches: u32,
    pub rays: RayCounts,
    /// Largest absolute difference of any channel of any pixel against the baseline image.
    pub max_abs_diff: f64,
}

/// Largest per-channel absolute difference between two images of one frame.
pub fn max_abs_diff(a: &Film, b: &Film) -> f64 {
    let (x, y) = (a.resolve(), b.resolve());
    if x.len() != y.len() {
        return f64::INFINITY;
    }
    x.iter()
        .zip(&y)
        .flat_map(|(p, q)| (0..3).map(move |c| (p[c] - q[c]).abs() as f64))
        .fold(0.0, f64::max)
}

/// Times every shape on adapter `adapter` (an index or name, as
/// `GpuRenderer::new` takes it), `reps` timed renders each, and compares
/// each image with `baseline`. `each` sees every point as it is measured
/// (progress output).
#[allow(clippy::too_many_arguments)]
pub fn sweep(
    adapter: &str,
    prepared: &PreparedFrame,
    rect: Rect,
    samples: u32,
    reps: usize,
    shapes: &[LaunchShape],
    baseline: &Film,
    mut each: impl FnMut(&SweepPoint),
) -> Vec<SweepPoint> {
    shapes
        .iter()
        .map(|&shape| {
            let result = GpuRenderer::new(Some(adapter), shape.options())
                .and_then(|r| {
                    Ok(run_interleaved(&[&r], prepared, rect, samples, reps)?
                        .pop()
                        .expect("one renderer, one timing"))
                })
                .map(|t| SweepTiming {
                    gpu: t.gpu,
                    trace: t.trace,
                    total: t.total,
                    readback: t.readback,
                    first: t.first,
                    dispatches: t.dispatches,
                    rays: t.film.rays,
                    max_abs_diff: max_abs_diff(&t.film, baseline),
                })
                .map_err(|e| e.to_string());
            let point = SweepPoint { shape, result };
            each(&point);
            point
        })
        .collect()
}
