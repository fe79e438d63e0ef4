//! Probe: one CPU render of a frame against the same frame cut into units,
//! with rayon's default splitting of the tiles and with one tile a piece.
use rayon::prelude::*;
use std::time::Instant;
use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::cpu::{TILE, render_tile};
use tracer_core::render::{Precision, PreparedFrame};
use tracer_core::scene::SceneDesc;

fn main() {
    let desc = SceneDesc::load("examples/resolution.toml").unwrap();
    let mut s = desc.render;
    let args: Vec<u32> = std::env::args()
        .skip(1)
        .map(|a| a.parse().unwrap())
        .collect();
    (s.width, s.height, s.samples) = (args[0], args[1], args[2]);
    let (uw, uh) = (args[3], args[4]);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let PreparedFrame::F32(w) = PreparedFrame::build(&desc, &s, 0, Precision::F32).unwrap() else {
        unreachable!()
    };
    let samples = SampleRange::all(s.samples);
    let render = |rect: Rect, fine: bool| {
        let tiles = rect.tiles(TILE);
        pool.install(|| {
            if fine {
                tiles
                    .par_iter()
                    .with_max_len(1)
                    .map(|&t| render_tile(&w, 0, t, samples))
                    .count()
            } else {
                tiles
                    .par_iter()
                    .map(|&t| render_tile(&w, 0, t, samples))
                    .count()
            }
        })
    };
    let units: Vec<Rect> = (0..s.height)
        .step_by(uh as usize)
        .flat_map(|y| {
            (0..s.width)
                .step_by(uw as usize)
                .map(move |x| Rect::new(x, y, uw.min(s.width - x), uh.min(s.height - y)))
        })
        .collect();
    for _ in 0..3 {
        for fine in [false, true] {
            let t = Instant::now();
            render(Rect::full(s.width, s.height), fine);
            let whole = t.elapsed().as_secs_f64();
            let t = Instant::now();
            for &u in &units {
                render(u, fine);
            }
            let parts = t.elapsed().as_secs_f64();
            println!(
                "{}: whole {whole:.3} s, {} units {parts:.3} s, ratio {:.3}",
                if fine {
                    "one tile a piece"
                } else {
                    "default split   "
                },
                units.len(),
                parts / whole
            );
        }
    }
}
