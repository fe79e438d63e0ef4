//! Where a BVH starts to pay off for sphere scenes: renders a floor plane and
//! N spheres (in a grid in front of the camera, plastic and chrome, two
//! lights; like the thesis's complexity scenes) with the plain loop and with
//! the tree, on one thread, and prints Mrays/s for each. The winner's
//! crossover sets `accel::SPHERE_BVH_MIN`.
//!
//!   cargo run --release -p tracer-core --example accel_crossover

use std::fmt::Write as _;
use std::time::Instant;
use tracer_core::film::WorkRegion;

use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::{CpuRenderer, PreparedFrame};
use tracer_core::scene::SceneDesc;
use tracer_core::world::World;

fn scene(n: usize) -> SceneDesc {
    let mut s = String::from(
        "[render]\nwidth = 400\nheight = 300\nsamples = 1\nmax_depth = 4\n\
         [camera]\nposition = [0, 2, -9]\nlook_at = [0, 0.8, 0]\n[world]\nambient = [0.2, 0.2, 0.2]\n\
         [materials.floor]\ndiffuse = [0.6, 0.6, 0.6]\nreflectivity = 0.3\n\
         [materials.plastic]\ndiffuse = [0.7, 0.1, 0.1]\nspecular = [0.6, 0.6, 0.6]\nshininess = 30\n\
         [materials.chrome]\ndiffuse = [0.2, 0.2, 0.2]\nspecular = [0.9, 0.9, 0.9]\nshininess = 80\nreflectivity = 0.8\n\
         [[lights]]\nposition = [-4, 6, -4]\n[[lights]]\nposition = [4, 5, -3]\n\
         [[objects]]\ntype = \"plane\"\nnormal = [0, 1, 0]\ndistance = 0\nmaterial = \"floor\"\n",
    );
    let side = (n as f64).sqrt().ceil() as usize;
    let r = 2.5 / side as f64;
    for i in 0..n {
        let (gx, gz) = (i % side, i / side);
        let x = -3.0 + 6.0 * (gx as f64 + 0.5) / side as f64;
        let z = -1.0 + 4.0 * (gz as f64 + 0.5) / side as f64;
        let m = if i % 2 == 0 { "plastic" } else { "chrome" };
        write!(s, "[[objects]]\ntype = \"sphere\"\ncenter = [{x}, {r}, {z}]\nradius = {r}\nmaterial = \"{m}\"\n").unwrap();
    }
    SceneDesc::parse(&s, "crossover.toml").expect("generated scene is valid")
}

/// CPU seconds used by this process (all threads): on a shared machine,
/// rays per CPU-second is steadier than rays per wall-clock second.
fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes into the zeroed struct we pass and reads nothing else.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

fn main() {
    let renderer = CpuRenderer::new(Some(1)).expect("thread pool");
    println!(
        "Mrays/s, 1 thread, best of 5 (default: BVH from {} spheres)\nspheres | loop                  | BVH",
        tracer_core::accel::SPHERE_BVH_MIN
    );
    for n in [1, 2, 4, 6, 8, 10, 12, 16, 24, 32, 64, 128] {
        let desc = scene(n);
        let rate = |bvh: bool| {
            let mut world: World<f32> = World::build(&desc, &desc.render, 0);
            world.set_accel(Some(bvh));
            let frame = PreparedFrame::F32(world);
            (0..5)
                .map(|_| {
                    let (t, c) = (Instant::now(), cpu_seconds());
                    let film = renderer
                        .render(
                            &frame,
                            WorkRegion::new(
                                0,
                                Rect::full(desc.render.width, desc.render.height),
                                SampleRange::all(1),
                            ),
                            &|_| {},
                        )
                        .expect("valid request");
                    let rays = film.rays.total() as f64 / 1e6;
                    (rays / t.elapsed().as_secs_f64(), rays / (cpu_seconds() - c))
                })
                .fold((0.0, 0.0), |a, b| (f64::max(a.0, b.0), f64::max(a.1, b.1)))
        };
        let (l, b) = (rate(false), rate(true));
        println!(
            "{n:7} | {:5.2} wall {:5.2} CPU | {:5.2} wall {:5.2} CPU",
            l.0, l.1, b.0, b.1
        );
    }
}
