//! GPU benchmark: the thesis scenes on the GPU and the CPU of the same
//! machine, and the launch-shape sweep (workgroup size x dispatch size).
//!
//!     cargo run --release -p tracer-core --example gpu_bench -- [--adapter NAME|INDEX] [--reps N] [--quick] [--no-sweep] [--no-cpu]
//!
//! `--quick`: two scenes, and a few launch shapes instead of the full grid.
//! Prints markdown tables (for docs/benchmarks.md). Times are medians of
//! `--reps` renders after 3 warm-up renders (the first builds the pipeline
//! and uploads the scene). "GPU" is the tracing passes' time from timestamp
//! queries (or, without them, host wall time from submission to completion,
//! read-back excluded); "total" is the whole render call: parameter upload,
//! tracing, read-back of the sums and conversion into a Film.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tracer_core::film::WorkRegion;

use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::gpu::{GpuOptions, GpuRenderer, Strategy, launch};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};

struct Args {
    adapter: Option<String>,
    reps: usize,
    quick: bool,
    sweep: bool,
    cpu: bool,
    sizes: Vec<(u32, u32)>,
}

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        adapter: None,
        reps: 7,
        quick: false,
        sweep: true,
        cpu: true,
        sizes: vec![(800, 600), (1920, 1080)],
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        match arg.as_str() {
            "--adapter" => a.adapter = Some(it.next().ok_or("--adapter needs a value")?),
            "--reps" => {
                a.reps = it
                    .next()
                    .ok_or("--reps needs a value")?
                    .parse()
                    .map_err(|e| format!("--reps: {e}"))?
            }
            "--quick" => a.quick = true,
            "--no-sweep" => a.sweep = false,
            "--no-cpu" => a.cpu = false,
            "--sizes" => {
                let v = it.next().ok_or("--sizes needs WxH[,WxH...]")?;
                a.sizes = v
                    .split(',')
                    .map(|p| {
                        let (w, h) = p
                            .split_once('x')
                            .ok_or(format!("--sizes: {p:?} is not WxH"))?;
                        Ok((
                            w.parse().map_err(|e| format!("--sizes: {e}"))?,
                            h.parse().map_err(|e| format!("--sizes: {e}"))?,
                        ))
                    })
                    .collect::<Result<_, String>>()?;
            }
            other => return Err(format!("unknown argument {other:?}")),
        }
    }
    a.reps = a.reps.max(1);
    Ok(a)
}

fn examples() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples")
}

fn ms(d: Duration) -> String {
    format!("{:.2}", d.as_secs_f64() * 1e3)
}

fn mean_abs_diff(a: &Film, b: &Film) -> f64 {
    let (x, y) = (a.resolve(), b.resolve());
    x.iter()
        .zip(&y)
        .map(|(p, q)| {
            (0..3)
                .map(|c| (p[c] - q[c]).abs() as f64)
                .fold(0.0, f64::max)
        })
        .sum::<f64>()
        / x.len() as f64
}

fn main() {
    if let Err(e) = real_main() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn real_main() -> Result<(), Box<dyn std::error::Error>> {
    let args = parse_args()?;
    let g = GpuRenderer::new(args.adapter.as_deref(), GpuOptions::default())?;
    let idx = g.adapter().index.to_string();
    let wave = GpuRenderer::new(
        Some(&idx),
        GpuOptions {
            strategy: Strategy::Wavefront,
            ..GpuOptions::default()
        },
    )?;
    let cpu = CpuRenderer::new(None)?;
    println!("# GPU benchmark\n");
    println!("- adapter: {}", g.adapter());
    println!(
        "- GPU time from: {}",
        if g.has_timestamps() {
            "timestamp queries"
        } else {
            "host wall time around the trace submissions (no timestamp queries)"
        }
    );
    println!(
        "- CPU renderer: {} threads; {} logical cores",
        cpu.threads(),
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    println!(
        "- options: {:?}; median of {} renders after 3 warm-up renders, stack and wavefront interleaved\n",
        g.options(),
        args.reps
    );

    let mut scenes = vec!["resolution.toml".to_string(), "depth.toml".to_string()];
    if !args.quick {
        for m in ["plastic", "chrome", "glass", "emerald"] {
            for n in [1, 3, 6, 9] {
                scenes.push(format!("complexity/{m}-{n}.toml"));
            }
        }
    }
    let sizes = &args.sizes;
    println!(
        "| scene | size | spp | rays | wavefront GPU ms | stack GPU ms | trace wall ms | read-back ms | total ms (with read-back) | first render ms | M rays/s (stack GPU) | M rays/s (stack total) | CPU ms | CPU M rays/s | GPU total vs CPU | mean abs diff vs CPU f32 |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for name in &scenes {
        let desc = SceneDesc::load(examples().join(name))?;
        for &(w, h) in sizes.iter() {
            let s = RenderSettings {
                width: w,
                height: h,
                samples: 4,
                ..desc.render
            };
            let prepared = PreparedFrame::build(&desc, &s, 0, Precision::F32)?;
            let mut runs = launch::run_interleaved(
                &[&g, &wave],
                &prepared,
                Rect::full(w, h),
                s.samples,
                args.reps,
            )?;
            let wr = runs.pop().expect("two runs");
            let r = runs.pop().expect("two runs");
            if wr.film.rays != r.film.rays {
                println!(
                    "<!-- {name}: wavefront traced {:?}, stack {:?} -->",
                    wr.film.rays, r.film.rays
                );
            }
            let rays = r.film.rays.total() as f64;
            // CPU: all scenes at 800x600, the resolution scene at both sizes.
            let cpu_cols = if args.cpu && (h == sizes[0].1 || name == "resolution.toml") {
                let t = Instant::now();
                let cf = cpu.render(
                    &prepared,
                    WorkRegion::new(0, Rect::full(w, h), SampleRange::all(4)),
                    &|_| {},
                )?;
                let ct = t.elapsed();
                format!(
                    "{} | {:.0} | {:.2}x | {:.1e}",
                    ms(ct),
                    cf.rays.total() as f64 / ct.as_secs_f64() / 1e6,
                    ct.as_secs_f64() / r.total.as_secs_f64(),
                    mean_abs_diff(&r.film, &cf)
                )
            } else {
                "- | - | - | -".to_string()
            };
            println!(
                "| {name} | {w}x{h} | 4 | {:.1} M | {} | {} | {} | {} | {} | {} | {:.0} | {:.0} | {cpu_cols} |",
                rays / 1e6,
                ms(wr.gpu),
                ms(r.gpu),
                ms(r.trace),
                ms(r.readback),
                ms(r.total),
                ms(r.first),
                rays / r.gpu.as_secs_f64() / 1e6,
                rays / r.total.as_secs_f64() / 1e6,
            );
        }
    }

    if args.sweep {
        let desc = SceneDesc::load(examples().join("resolution.toml"))?;
        let (w, h) = *sizes.last().ok_or("no --sizes")?;
        let s = RenderSettings {
            width: w,
            height: h,
            samples: 4,
            ..desc.render
        };
        let prepared = PreparedFrame::build(&desc, &s, 0, Precision::F32)?;
        let rect = Rect::full(w, h);
        let baseline = launch::run_interleaved(&[&g], &prepared, rect, s.samples, 1)?
            .pop()
            .expect("one timing")
            .film;
        let points = launch::sweep(
            &idx,
            &prepared,
            rect,
            s.samples,
            args.reps.min(5),
            &launch::sweep_shapes(args.quick),
            &baseline,
            |_| {},
        );
        for (strategy, title) in [
            (Strategy::Stack, format!("Launch-shape sweep: resolution scene, {w}x{h}, 4 spp, GPU ms / trace wall ms (medians)")),
            (Strategy::Wavefront, "Wavefront sweep: same frame, GPU ms / trace wall ms (medians); dispatches are capped at 65535 workgroups".to_string()),
        ] {
            let pts: Vec<&launch::SweepPoint> = points.iter().filter(|p| p.shape.strategy == strategy).collect();
            let mut budgets: Vec<u64> = pts.iter().map(|p| p.shape.dispatch_pixel_samples).collect();
            budgets.sort();
            budgets.dedup();
            let mut shapes: Vec<(u32, u32)> = vec![];
            for p in &pts {
                if !shapes.contains(&p.shape.workgroup) {
                    shapes.push(p.shape.workgroup);
                }
            }
            println!("\n## {title}\n");
            print!("| workgroup \\ pixel-samples per dispatch |");
            for b in &budgets {
                print!(" {b} |");
            }
            println!("\n|---|{}", "---|".repeat(budgets.len()));
            for wg in shapes {
                print!("| {}x{} |", wg.0, wg.1);
                for &b in &budgets {
                    match pts.iter().find(|p| p.shape.workgroup == wg && p.shape.dispatch_pixel_samples == b).map(|p| &p.result) {
                        Some(Ok(t)) if t.max_abs_diff == 0.0 => print!(" {} / {} |", ms(t.gpu), ms(t.trace)),
                        Some(Ok(t)) => print!(" {} / {} (image differs by {:.1e}) |", ms(t.gpu), ms(t.trace), t.max_abs_diff),
                        Some(Err(e)) => print!(" n/a ({e}) |"),
                        None => print!(" - |"),
                    }
                }
                println!();
            }
        }
    }
    Ok(())
}
