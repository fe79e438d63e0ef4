//! CPU renderer throughput on a scene file (default: the thesis's resolution
//! scene at 800x600, 4 samples, depth 10), f32, best of 5, on 1 thread and on
//! all threads. Prints wall and CPU seconds: on a shared machine rays per
//! CPU-second is the per-core throughput.
//!
//!   cargo run --release -p tracer-core --no-default-features --example cpu_speed -- [SCENE] [THREADS...]

use std::time::Instant;
use tracer_core::film::WorkRegion;

use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::SceneDesc;

const REPEATS: usize = 5;

fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes into the zeroed struct we pass and reads nothing else.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let path = args.next().unwrap_or_else(|| {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/resolution.toml").to_string()
    });
    let mut threads: Vec<usize> = args.map(|a| a.parse()).collect::<Result<_, _>>()?;
    if threads.is_empty() {
        threads = vec![
            1,
            std::thread::available_parallelism().map_or(1, |n| n.get()),
        ];
    }
    let desc = SceneDesc::load(std::path::Path::new(&path))?;
    let settings = desc.render;
    let prepared = PreparedFrame::build(&desc, &settings, 0, Precision::F32)?;
    let rect = Rect::full(settings.width, settings.height);
    let samples = SampleRange::all(settings.samples);
    println!(
        "{path}: {}x{}, {} spp, depth {}, f32, best of {REPEATS}, stream SIMD level {}",
        settings.width,
        settings.height,
        settings.samples,
        settings.max_depth,
        tracer_core::simd::level().name()
    );
    for n in threads {
        let r = CpuRenderer::new(Some(n))?;
        let (mut wall, mut cpu, mut rays, mut counts) = (f64::MAX, f64::MAX, 0, Default::default());
        for _ in 0..REPEATS {
            let (t, c) = (Instant::now(), cpu_seconds());
            let film = r.render(&prepared, WorkRegion::new(0, rect, samples), &|_| {})?;
            wall = wall.min(t.elapsed().as_secs_f64());
            cpu = cpu.min(cpu_seconds() - c);
            rays = film.rays.total();
            counts = film.rays;
        }
        println!(
            "  {n} thread(s): {:.3} s wall, {:.3} s CPU, {rays} rays: {:.1} Mrays/s wall, {:.1} Mrays per CPU-second",
            wall,
            cpu,
            rays as f64 / wall / 1e6,
            rays as f64 / cpu / 1e6
        );
        let c: tracer_core::film::RayCounts = counts;
        println!(
            "    rays: {} primary, {} shadow, {} reflection, {} refraction",
            c.primary, c.shadow, c.reflection, c.refraction
        );
    }
    Ok(())
}
