//! Mesh benchmark: BVH build time and memory, and throughput for primary
//! rays (1024x768 camera rays, one per pixel; closest hit, one by one and
//! in packets of 4x4 pixels), shadow rays from the primary hits to a point
//! light (one by one and in packets) and incoherent rays (one random
//! hemisphere ray from each primary hit; closest hit and occlusion), on one
//! thread and on all threads.
//!
//!   cargo run --release -p tracer-core --example mesh_bench -- [--gpu] [--no-cpu] [MODEL ...]
//!
//! Without model arguments it reads the Stanford bunny and dragon from
//! ../shared/meshes (they may not be committed: see examples/models/README.md)
//! and skips, with a message, any that is not there.
//!
//! `--gpu` adds the GPU backend (BVH traversal in bvh.wgsl) on the same
//! model and camera: whole Whitted renders at 1920x1080, 4 samples, of (a)
//! a diffuse model and one light (primary + shadow rays) and (b) a mirror
//! model, depth 2 (adds reflection rays off the surface, which scatter, and
//! their shadow rays); rays per second of GPU time (timestamp queries) and
//! of wall time (whole render calls), and the GPU image against the CPU's
//! f32 render of the same scene. `--no-cpu` skips the CPU ray timings.

use std::path::{Path, PathBuf};
use std::time::Instant;
use tracer_core::film::WorkRegion;

use glam::Vec3A;
use rayon::prelude::*;
use tracer_core::bvh::closest_hits_at;
use tracer_core::geometry::PrimId;
use tracer_core::math::{Ray, offset_origin};
use tracer_core::mesh::Mesh;
use tracer_core::sampling::hash_u32;
use tracer_core::scene::SceneDesc;
use tracer_core::simd::SimdLevel;
use tracer_core::world::World;

const WIDTH: u32 = 1024;
const HEIGHT: u32 = 768;
const REPEATS: usize = 5;

thread_local! {
    /// GPU render size (width, height, samples); `--gpu-size`.
    static GPU_SIZE: std::cell::Cell<(u32, u32, u32)> = const { std::cell::Cell::new((1920, 1080, 4)) };
}

/// CPU seconds used by this process so far (all threads). On a shared
/// machine wall time includes waiting for the CPU; rays per CPU-second is
/// the per-core throughput.
fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes into the zeroed struct we pass and reads nothing else.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Best (wall, CPU) seconds of `REPEATS` runs of `f`.
fn best_of(f: &mut dyn FnMut()) -> (f64, f64) {
    let mut best = (f64::MAX, f64::MAX);
    for _ in 0..REPEATS {
        let (t, c) = (Instant::now(), cpu_seconds());
        f();
        best = (
            best.0.min(t.elapsed().as_secs_f64()),
            best.1.min(cpu_seconds() - c),
        );
    }
    best
}

/// A packet of shadow rays: the rays, their limits and their start primitives.
type ShadowBlock = (Vec<Ray<f32>>, Vec<f32>, Vec<PrimId>);

fn main() {
    let mut gpu = false;
    let mut cpu = true;
    let mut args: Vec<PathBuf> = Vec::new();
    for a in std::env::args().skip(1) {
        match a.as_str() {
            "--gpu" => gpu = true,
            "--no-cpu" => cpu = false,
            // Smaller GPU renders (e.g. 192x108x1 on a software adapter).
            x if x.starts_with("--gpu-size=") => {
                let v: Vec<u32> = x["--gpu-size=".len()..]
                    .split('x')
                    .filter_map(|n| n.parse().ok())
                    .collect();
                match v[..] {
                    [w, h, s] if w > 0 && h > 0 && s > 0 => GPU_SIZE.with(|g| g.set((w, h, s))),
                    _ => {
                        eprintln!("--gpu-size=WxHxS, e.g. --gpu-size=1920x1080x4");
                        std::process::exit(2);
                    }
                }
            }
            _ => args.push(PathBuf::from(a)),
        }
    }
    let models = if args.is_empty() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/meshes");
        vec![
            root.join("stanford-bunny.obj"),
            root.join("dragon_vrip.ply.gz"),
        ]
    } else {
        args
    };
    let threads = rayon::current_num_threads();
    println!(
        "mesh_bench: {WIDTH}x{HEIGHT} primary rays + as many incoherent rays, f32, best of {REPEATS}; {threads} threads available"
    );
    for path in models {
        if !path.exists() {
            println!("\n{}: not found, skipped", path.display());
            continue;
        }
        if let Err(e) = bench(&path, threads, cpu, gpu) {
            println!("\n{}: {e}", path.display());
        }
    }
}

fn bench(path: &Path, threads: usize, cpu: bool, gpu: bool) -> Result<(), String> {
    let t = Instant::now();
    let mesh = Mesh::load(path, false).map_err(|e| e.to_string())?;
    let load = t.elapsed();
    let (lo, hi) = mesh
        .positions
        .iter()
        .fold(([f32::MAX; 3], [f32::MIN; 3]), |(lo, hi), p| {
            (
                [0, 1, 2].map(|k| lo[k].min(p[k])),
                [0, 1, 2].map(|k| hi[k].max(p[k])),
            )
        });
    let c = [0, 1, 2].map(|k| (lo[k] + hi[k]) as f64 / 2.0);
    let diag = (0..3)
        .map(|k| ((hi[k] - lo[k]) as f64).powi(2))
        .sum::<f64>()
        .sqrt();
    // Camera in front (+z, where both models face), framing the model.
    let cam = [c[0], c[1] + 0.1 * diag, c[2] + 1.0 * diag];
    let scene_src = format!(
        "[render]\nwidth = {WIDTH}\nheight = {HEIGHT}\nsamples = 1\n[camera]\nposition = {cam:?}\nlook_at = {c:?}\nfov_y = 40\n\
         [materials.grey]\ndiffuse = [0.8, 0.8, 0.8]\n[[objects]]\ntype = \"mesh\"\npath = {:?}\nmaterial = \"grey\"\n",
        path.display().to_string()
    );
    let scene = SceneDesc::parse(&scene_src, "mesh_bench.toml").map_err(|e| e.to_string())?;

    println!(
        "\n{}: {} triangles, {} vertices (loaded in {:.0} ms)",
        path.display(),
        mesh.triangles.len(),
        mesh.positions.len(),
        load.as_secs_f64() * 1e3
    );
    let mut world: World<f32> = World::build(&scene, &scene.render, 0);
    // Build time: the tree alone (boxes in, flattened nodes out), as `Bvh::build` times it.
    let build_with = |world: &mut World<f32>, n: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .expect("thread pool");
        let mut best = (f64::MAX, f64::MAX);
        for _ in 0..REPEATS {
            let c = cpu_seconds();
            pool.install(|| world.set_accel(Some(true)));
            let wall = world
                .accel
                .as_ref()
                .map_or(0.0, |b| b.stats.build_time.as_secs_f64());
            best = (best.0.min(wall), best.1.min(cpu_seconds() - c));
        }
        best
    };
    let b1 = build_with(&mut world, 1);
    let bn = build_with(&mut world, threads);
    let stats = world.accel.as_ref().ok_or("no BVH was built")?.stats;
    println!(
        "  BVH build: {:.1} ms wall on 1 thread ({:.1} ms CPU incl. reordering), {:.1} ms wall on {threads}; {} nodes (4-wide), {} leaves, depth {}, stack {}, max leaf {}, {:.1} MiB (nodes+refs+packets) + {:.1} MiB triangles, {} degenerate dropped",
        b1.0 * 1e3,
        b1.1 * 1e3,
        bn.0 * 1e3,
        stats.nodes,
        stats.leaves,
        stats.depth,
        stats.stack,
        stats.max_leaf_size,
        stats.bytes as f64 / (1 << 20) as f64,
        world.triangle_bytes() as f64 / (1 << 20) as f64,
        world.degenerate_triangles
    );

    // Primary rays through pixel centres.
    let primary: Vec<Ray<f32>> = (0..HEIGHT)
        .flat_map(|y| (0..WIDTH).map(move |x| (x, y)))
        .map(|(x, y)| world.camera.ray(x as f32 + 0.5, y as f32 + 0.5))
        .collect();
    let hits: Vec<Option<(f32, PrimId)>> = primary
        .iter()
        .map(|r| world.closest_hit(r, PrimId::NONE))
        .collect();
    // Incoherent rays: uniform on the hemisphere around the facing normal, from each hit.
    let secondary: Vec<(Ray<f32>, PrimId)> = primary
        .iter()
        .zip(&hits)
        .enumerate()
        .filter_map(|(i, (r, h))| {
            let (t, id) = (*h)?;
            let (p, n, _) = world.surface(id, r.at(t));
            let n = if n.dot(r.dir) < 0.0 { n } else { -n };
            let u = |k: u32| hash_u32(i as u32 * 4 + k) as f32 / u32::MAX as f32 * 2.0 - 1.0;
            let d = loop_free_sphere(u(0), u(1));
            let d = if d.dot(n) < 0.0 { -d } else { d };
            Some((Ray::new(offset_origin::<f32>(p, n), d), id))
        })
        .collect();
    println!(
        "  {} of {} primary rays hit; {} incoherent rays",
        secondary.len(),
        primary.len(),
        secondary.len()
    );
    // The same primary rays in packets of 4x4 pixels (`World::closest_hits`),
    // checked against the single-ray answers: they must be the same bits.
    let pr = &primary;
    let blocks: Vec<Vec<Ray<f32>>> = (0..HEIGHT.div_ceil(4))
        .flat_map(|by| (0..WIDTH.div_ceil(4)).map(move |bx| (bx, by)))
        .map(|(bx, by)| {
            (by * 4..(by * 4 + 4).min(HEIGHT))
                .flat_map(|y| {
                    (bx * 4..(bx * 4 + 4).min(WIDTH)).map(move |x| pr[(y * WIDTH + x) as usize])
                })
                .collect()
        })
        .collect();
    let packet_hits = |block: &[Ray<f32>]| {
        let mut out = [None; 16];
        world.closest_hits(block, PrimId::NONE, &mut out[..block.len()]);
        out
    };
    let differ: usize = blocks
        .iter()
        .map(|b| {
            let got = packet_hits(b);
            b.iter()
                .zip(got)
                .filter(|(r, g)| {
                    g.map(|(t, id)| (t.to_bits(), id))
                        != world
                            .closest_hit(r, PrimId::NONE)
                            .map(|(t, id)| (t.to_bits(), id))
                })
                .count()
        })
        .sum();
    // The tree walk alone with the AVX-512 node test (no planes in this scene).
    let tree = world.accel.as_ref().ok_or("no BVH was built")?;
    let packet_hits_avx512 = |block: &[Ray<f32>]| {
        let n = block.len();
        let (mut best, mut found) = ([f32::INFINITY; 16], [PrimId::NONE; 16]);
        closest_hits_at(
            SimdLevel::Avx512,
            &world,
            tree,
            block,
            &mut best[..n],
            &mut found[..n],
            PrimId::NONE,
        );
        found[..n].iter().filter(|&&id| id != PrimId::NONE).count()
    };
    let wide = SimdLevel::Avx512.is_available();
    println!("  packets of 4x4 primary rays: {differ} answers differ from single rays");
    // Shadow rays from each block's hits to a point light above, left and in
    // front of the model: coherent (neighbouring points, one light), traced
    // one by one and as each block's packet (`World::occluded_many`).
    let light = Vec3A::new(
        (c[0] - 0.6 * diag) as f32,
        (c[1] + 0.8 * diag) as f32,
        (c[2] + 0.6 * diag) as f32,
    );
    let shadow_blocks: Vec<ShadowBlock> = blocks
        .iter()
        .map(|b| {
            let mut out = (Vec::new(), Vec::new(), Vec::new());
            for (r, h) in b.iter().zip(packet_hits(b)) {
                let Some((t, id)) = h else { continue };
                let (p, n, _) = world.surface(id, r.at(t));
                let to = light - p;
                let n = if n.dot(to) >= 0.0 { n } else { -n };
                let o = offset_origin::<f32>(p, n);
                out.0.push(Ray::new(o, (light - o).normalize()));
                out.1.push((light - o).length() * 0.9999);
                out.2.push(id);
            }
            out
        })
        .collect();
    let shadow_count: usize = shadow_blocks.iter().map(|b| b.0.len()).sum();
    let occluded_packets = |(r, t, s): &(Vec<Ray<f32>>, Vec<f32>, Vec<PrimId>)| {
        let mut out = [false; 16];
        world.occluded_many(r, t, s, &mut out[..r.len()]);
        out
    };
    let (mut shadow_differ, mut shadow_blocked) = (0, 0);
    for b in &shadow_blocks {
        let got = occluded_packets(b);
        for (j, ((r, &t), &id)) in b.0.iter().zip(&b.1).zip(&b.2).enumerate() {
            let want = world.occluded(r, t, id);
            shadow_differ += (got[j] != want) as usize;
            shadow_blocked += want as usize;
        }
    }
    println!(
        "  {shadow_count} shadow rays to a point light, {shadow_blocked} blocked; in packets: {shadow_differ} answers differ from single rays"
    );

    if gpu && let Err(e) = gpu_bench(path, cam, c) {
        println!("  GPU: {e}");
    }
    if !cpu {
        return Ok(());
    }
    for n in [1, threads] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .expect("thread pool");
        let time = |f: &(dyn Fn() -> usize + Sync)| {
            best_of(&mut || {
                std::hint::black_box(pool.install(f));
            })
        };
        let tp = time(&|| {
            primary
                .par_chunks(4096)
                .map(|c| {
                    c.iter()
                        .filter(|r| world.closest_hit(r, PrimId::NONE).is_some())
                        .count()
                })
                .sum()
        });
        let tk = time(&|| {
            blocks
                .par_chunks(256)
                .map(|c| {
                    c.iter()
                        .map(|b| packet_hits(b).iter().filter(|h| h.is_some()).count())
                        .sum::<usize>()
                })
                .sum()
        });
        let tw = wide.then(|| {
            time(&|| {
                blocks
                    .par_chunks(256)
                    .map(|c| c.iter().map(|b| packet_hits_avx512(b)).sum::<usize>())
                    .sum()
            })
        });
        let ti = time(&|| {
            secondary
                .par_chunks(4096)
                .map(|c| {
                    c.iter()
                        .filter(|(r, id)| world.closest_hit(r, *id).is_some())
                        .count()
                })
                .sum()
        });
        let ts = time(&|| {
            secondary
                .par_chunks(4096)
                .map(|c| {
                    c.iter()
                        .filter(|(r, id)| world.occluded(r, f32::INFINITY, *id))
                        .count()
                })
                .sum()
        });
        let tsh = time(&|| {
            shadow_blocks
                .par_chunks(256)
                .map(|c| {
                    c.iter()
                        .map(|(r, t, s)| {
                            r.iter()
                                .zip(t)
                                .zip(s)
                                .filter(|((r, t), s)| world.occluded(r, **t, **s))
                                .count()
                        })
                        .sum::<usize>()
                })
                .sum()
        });
        let tshp = time(&|| {
            shadow_blocks
                .par_chunks(256)
                .map(|c| {
                    c.iter()
                        .map(|b| occluded_packets(b).iter().filter(|&&x| x).count())
                        .sum::<usize>()
                })
                .sum()
        });
        let m = |rays: usize, (wall, cpu): (f64, f64)| {
            format!(
                "{:.2} ({:.2}/CPU-s)",
                rays as f64 / wall / 1e6,
                rays as f64 / cpu / 1e6
            )
        };
        println!(
            "  {n} thread{}: Mrays/s wall (per CPU-second): primary {}, primary in 4x4 packets {} ({} node test; AVX-512: {}), shadow {}, shadow in packets {}, incoherent closest-hit {}, incoherent occlusion {}",
            if n == 1 { " " } else { "s" },
            m(primary.len(), tp),
            m(primary.len(), tk),
            tracer_core::bvh::render_level().name(),
            tw.map_or("no AVX-512F".to_string(), |t| m(primary.len(), t)),
            m(shadow_count, tsh),
            m(shadow_count, tshp),
            m(secondary.len(), ti),
            m(secondary.len(), ts)
        );
    }
    Ok(())
}

/// A unit vector from two numbers in [-1, 1] (uniform on the sphere).
fn loop_free_sphere(a: f32, b: f32) -> Vec3A {
    let z = a;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = std::f32::consts::PI * b;
    Vec3A::new(r * phi.cos(), r * phi.sin(), z)
}

/// The GPU part (`--gpu`): see the module docs.
fn gpu_bench(path: &Path, cam: [f64; 3], look_at: [f64; 3]) -> Result<(), String> {
    use tracer_core::film::{Rect, SampleRange};
    use tracer_core::render::gpu::{GpuOptions, GpuRenderer};
    use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};

    let g = GpuRenderer::new(None, GpuOptions::default()).map_err(|e| e.to_string())?;
    println!(
        "  GPU: {} (timestamps: {})",
        g.adapter(),
        g.has_timestamps()
    );
    let scene = |(w, h, samples): (u32, u32, u32), material: &str, depth: u32| {
        let src = format!(
            "[render]\nwidth = {w}\nheight = {h}\nsamples = {samples}\nmax_depth = {depth}\n[camera]\nposition = {cam:?}\nlook_at = {look_at:?}\nfov_y = 40\n\
             [world]\nambient = [0.1, 0.1, 0.1]\nbackground = [0.2, 0.3, 0.5]\n\
             [materials.grey]\ndiffuse = [0.8, 0.8, 0.8]\nspecular = [0.3, 0.3, 0.3]\nshininess = 20\n\
             [materials.mirror]\ndiffuse = [0.2, 0.2, 0.2]\nreflectivity = 0.7\n\
             [[lights]]\nposition = [{}, {}, {}]\n\
             [[objects]]\ntype = \"mesh\"\npath = {:?}\nmaterial = \"{material}\"\n",
            cam[0] - (cam[2] - look_at[2]),
            cam[1] + (cam[2] - look_at[2]),
            cam[2],
            path.display().to_string()
        );
        SceneDesc::parse(&src, "mesh_bench.toml").map_err(|e| e.to_string())
    };
    for (label, material, depth) in [
        ("diffuse, depth 0 (primary + shadow)", "grey", 0),
        ("mirror, depth 2 (+ reflection, their shadows)", "mirror", 2),
    ] {
        let (w, h, spp) = GPU_SIZE.with(|g| g.get());
        let desc = scene((w, h, spp), material, depth)?;
        let t = Instant::now();
        let frame = PreparedFrame::build(&desc, &desc.render, 0, Precision::F32)
            .map_err(|e| e.to_string())?;
        let build = t.elapsed();
        let render = || {
            g.render(
                &frame,
                WorkRegion::new(0, Rect::full(w, h), SampleRange::all(spp)),
                &|_| {},
            )
            .map_err(|e| e.to_string())
        };
        let t = Instant::now();
        let first = render()?;
        let warm = t.elapsed();
        let mut gpu_s = Vec::new();
        let mut wall_s = Vec::new();
        for _ in 0..5 {
            let t = Instant::now();
            let film = render()?;
            wall_s.push(t.elapsed().as_secs_f64());
            if film.sums != first.sums {
                return Err("two GPU renders of the same frame differ".into());
            }
            let st = g.last_stats();
            gpu_s.push(st.gpu_time.unwrap_or(st.trace_wall).as_secs_f64());
        }
        let median = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let (gt, wt) = (median(&mut gpu_s), median(&mut wall_s));
        let r = first.rays;
        let total = r.primary + r.shadow + r.reflection + r.refraction;
        println!(
            "  GPU {w}x{h} {spp} spp, {label}: rays primary {} shadow {} reflection {}; GPU time {:.2} ms -> {:.0} Mrays/s ({:.0} M primary/s); whole render call {:.1} ms -> {:.0} Mrays/s; first render (upload, pipeline) {:.0} ms; world build {:.0} ms",
            r.primary,
            r.shadow,
            r.reflection,
            gt * 1e3,
            total as f64 / gt / 1e6,
            r.primary as f64 / gt / 1e6,
            wt * 1e3,
            total as f64 / wt / 1e6,
            warm.as_secs_f64() * 1e3,
            build.as_secs_f64() * 1e3
        );

        // Correctness: the same scene, smaller, on the CPU (f32, all threads).
        let (cw, ch) = (w.min(480), h.min(270));
        let small = scene((cw, ch, 1), material, depth)?;
        let frame = PreparedFrame::build(&small, &small.render, 0, Precision::F32)
            .map_err(|e| e.to_string())?;
        let gf = g
            .render(
                &frame,
                WorkRegion::new(0, Rect::full(cw, ch), SampleRange::all(1)),
                &|_| {},
            )
            .map_err(|e| e.to_string())?;
        let cf = CpuRenderer::new(None)
            .map_err(|e| e.to_string())?
            .render(
                &frame,
                WorkRegion::new(0, Rect::full(cw, ch), SampleRange::all(1)),
                &|_| {},
            )
            .map_err(|e| e.to_string())?;
        let (a, b) = (gf.resolve(), cf.resolve());
        let mut mean = 0.0f64;
        let mut over = 0;
        for (p, q) in a.iter().zip(&b) {
            let d = (0..3).map(|k| (p[k] - q[k]).abs()).fold(0.0f32, f32::max);
            mean += d as f64;
            over += (d > 2.0 / 255.0) as usize;
        }
        mean /= a.len() as f64;
        println!(
            "    vs CPU f32 at {cw}x{ch}: mean |gpu - cpu| {mean:.2e}, {over} of {} pixels over 2/255 ({:.3}%); rays GPU {:?} CPU {:?}",
            a.len(),
            over as f64 * 100.0 / a.len() as f64,
            gf.rays,
            cf.rays
        );
    }
    Ok(())
}
