//! The CPU stream renderer (`render::cpu::stream`) against the recursive
//! reference (`render::cpu::render_tile_recursive`, one ray at a time
//! through `whitted::trace`): the same rays and the same bits, at every
//! SIMD level and for any split of the work.

mod common;

use common::*;
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::cpu::{SimdLevel, render_tile_recursive, stream};
use tracer_core::render::{Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};
use tracer_core::world::World;

fn world(desc: &SceneDesc, settings: &RenderSettings) -> World<f32> {
    match PreparedFrame::build(desc, settings, 0, Precision::F32).expect("settings are valid") {
        PreparedFrame::F32(w) => w,
        PreparedFrame::F64(_) => unreachable!("asked for f32"),
    }
}

/// Renders the whole image tile by tile with `tile_fn`.
fn render(
    w: &World<f32>,
    size: u32,
    samples: SampleRange,
    tile_fn: &dyn Fn(Rect, SampleRange) -> Film,
) -> Film {
    let full = Rect::full(w.settings.width, w.settings.height);
    let mut film = Film::new(full);
    for tile in full.tiles(size) {
        // Adds sums, counts, ray counts and non-finite counts.
        film.merge(&tile_fn(tile, samples))
            .expect("tiles lie inside the image");
    }
    film
}

/// Every stream-capable scene the tests know: the examples (thesis
/// experiments, showcase), the hard cases, and the hard-case test scenes.
fn scenes() -> Vec<(String, SceneDesc, RenderSettings)> {
    let dir = examples_dir();
    let mut out = vec![];
    for d in [dir.clone(), dir.join("complexity"), dir.join("hard")] {
        let mut paths: Vec<_> = std::fs::read_dir(&d)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "toml"))
            .collect();
        paths.sort();
        for p in paths {
            let desc = SceneDesc::load(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            let settings = RenderSettings {
                width: 96,
                height: 72,
                ..desc.render
            };
            out.push((p.display().to_string(), desc, settings));
        }
    }
    for (name, src) in [
        ("huge sphere floor", HUGE_SPHERE_FLOOR_SCENE),
        ("light on surface", LIGHT_ON_SURFACE_SCENE),
    ] {
        let desc = scene(src);
        let settings = RenderSettings {
            width: 96,
            height: 72,
            ..desc.render
        };
        out.push((name.to_string(), desc, settings));
    }
    let (desc, settings) = nested_glass_scene();
    out.push((
        "nested glass (hard-case settings)".to_string(),
        desc,
        settings,
    ));
    out
}

#[test]
fn stream_gives_the_recursive_renderers_bits_on_every_scene() {
    let mut checked = 0;
    for (name, desc, settings) in scenes() {
        let w = world(&desc, &settings);
        if !stream::supports(&w) {
            continue; // meshes and BVH scenes keep the recursive path
        }
        let samples = SampleRange::all(settings.samples);
        let level = SimdLevel::detect();
        let fast = render(&w, 16, samples, &|t, s| {
            stream::render_tile(&w, 0, t, s, level)
        });
        let reference = render(&w, 16, samples, &|t, s| render_tile_recursive(&w, 0, t, s));
        assert_eq!(
            fast.rays, reference.rays,
            "{name}: the stream renderer must trace exactly the recursive renderer's rays"
        );
        assert_eq!(
            fast.nonfinite, 0,
            "{name}: a NaN or infinite sample reached the film"
        );
        assert_eq!(reference.nonfinite, 0, "{name}");
        assert!(
            fast.rays.total() > fast.rays.primary,
            "{name}: the scene should spawn secondary or shadow rays"
        );
        assert_finite(&fast.resolve());
        // Bit for bit: the same IEEE operations in the same order (see
        // `render/cpu/stream.rs`). Report how far off a failure is.
        if fast != reference {
            let d = diff(&fast.resolve(), &reference.resolve(), 1e-6);
            panic!(
                "{name}: {} of {} pixels differ from the recursive renderer by more than 1e-6 (largest {:e})",
                d.over, d.pixels, d.max
            );
        }
        checked += 1;
    }
    assert!(
        checked >= 24,
        "expected every example and hard case to take the stream path, checked {checked}"
    );
}

#[test]
fn every_simd_level_gives_the_same_bits() {
    let levels = SimdLevel::available();
    eprintln!("SIMD levels on this machine: {levels:?}");
    for (name, desc, settings) in scenes() {
        let w = world(&desc, &settings);
        if !stream::supports(&w) {
            continue;
        }
        let samples = SampleRange::all(settings.samples);
        let base = render(&w, 16, samples, &|t, s| {
            stream::render_tile(&w, 0, t, s, SimdLevel::Baseline)
        });
        for &level in &levels[1..] {
            let other = render(&w, 16, samples, &|t, s| {
                stream::render_tile(&w, 0, t, s, level)
            });
            assert!(
                other == base,
                "{name}: SIMD level {level:?} differs from the baseline"
            );
        }
    }
}

#[test]
fn tiles_batches_and_sample_ranges_do_not_change_a_sample() {
    // One big tile (several batches of primary rays), odd tiles, and sample
    // ranges split in two, all against 16x16 tiles over all samples.
    let desc = SceneDesc::load(examples_dir().join("resolution.toml")).unwrap();
    let settings = RenderSettings {
        width: 90,
        height: 70,
        samples: 9,
        ..desc.render
    };
    let w = world(&desc, &settings);
    assert!(stream::supports(&w));
    let level = SimdLevel::detect();
    let all = SampleRange::all(9);
    let whole = render(&w, 16, all, &|t, s| stream::render_tile(&w, 0, t, s, level));
    let one_tile = render(&w, 90, all, &|t, s| stream::render_tile(&w, 0, t, s, level));
    assert!(
        one_tile == whole,
        "a 90x70 tile renders differently from 16x16 tiles"
    );
    let odd = render(&w, 7, all, &|t, s| stream::render_tile(&w, 0, t, s, level));
    assert!(
        odd == whole,
        "7x7 tiles render differently from 16x16 tiles"
    );
    let mut split = render(&w, 16, SampleRange::new(0, 4), &|t, s| {
        stream::render_tile(&w, 0, t, s, level)
    });
    let rest = render(&w, 23, SampleRange::new(4, 9), &|t, s| {
        stream::render_tile(&w, 0, t, s, level)
    });
    split.merge(&rest).unwrap();
    assert!(split == whole, "sample ranges 0..4 + 4..9 differ from 0..9");
}

#[test]
fn every_sampler_gives_the_recursive_renderers_bits() {
    // The stream renderer computes the grid's offsets once per tile and the
    // other patterns' per sample: both must place samples as the reference
    // does, for any frame and sample range.
    use tracer_core::sampling::Sampler;
    let desc = SceneDesc::load(examples_dir().join("resolution.toml")).unwrap();
    for (sampler, count) in [
        (Sampler::Grid, 4),
        (Sampler::Grid, 3),
        (Sampler::Jittered, 4),
        (Sampler::Jittered, 5),
    ] {
        let settings = RenderSettings {
            width: 40,
            height: 30,
            samples: count,
            sampler,
            ..desc.render
        };
        let w = world(&desc, &settings);
        for frame in [0, 3] {
            for samples in [SampleRange::all(count), SampleRange::new(1, count)] {
                let fast = render(&w, 16, samples, &|t, s| {
                    stream::render_tile(&w, frame, t, s, SimdLevel::detect())
                });
                let reference = render(&w, 16, samples, &|t, s| {
                    render_tile_recursive(&w, frame, t, s)
                });
                assert!(
                    fast == reference,
                    "{sampler:?} {count} spp, frame {frame}, samples {samples:?}: differs from the recursive renderer"
                );
            }
        }
    }
}

#[test]
fn many_primitives_give_the_recursive_renderers_bits() {
    // More primitives than the shading's selection gather takes (16 table
    // entries): the scalar gather must agree too. The examples have at most
    // 14; ten spheres would take the BVH (recursive) path, so add planes.
    let mut src = std::fs::read_to_string(examples_dir().join("resolution.toml")).unwrap();
    let materials = ["plastic", "chrome", "glass", "emerald", "floor"];
    for (k, material) in materials.iter().take(4).enumerate() {
        let x = k as f64 * 1.6 - 2.4;
        src += &format!(
            "\n[[objects]]\ntype = \"sphere\"\ncenter = [{x}, 0.4, -3.0]\nradius = 0.4\nmaterial = \"{material}\"\n"
        );
    }
    // Walls around the scene, some behind others.
    for (k, (n, d)) in [
        ([1, 0, 0], -8.0),
        ([-1, 0, 0], -8.0),
        ([0, 0, -1], -12.0),
        ([0, -1, 0], -9.0),
        ([0, 0, 1], -14.0),
    ]
    .iter()
    .enumerate()
    {
        for extra in [0.0, 1.5] {
            src += &format!(
                "\n[[objects]]\ntype = \"plane\"\nnormal = {n:?}\ndistance = {}\nmaterial = \"{}\"\n",
                d - extra,
                materials[k]
            );
        }
    }
    let desc = scene(&src);
    let settings = RenderSettings {
        width: 48,
        height: 36,
        ..desc.render
    };
    let w = world(&desc, &settings);
    assert!(stream::supports(&w) && w.spheres.len() + w.planes.len() == 19);
    let samples = SampleRange::all(settings.samples);
    let reference = render(&w, 16, samples, &|t, s| render_tile_recursive(&w, 0, t, s));
    for level in SimdLevel::available() {
        let fast = render(&w, 16, samples, &|t, s| {
            stream::render_tile(&w, 0, t, s, level)
        });
        assert!(
            fast == reference,
            "{level:?}: 19 primitives render differently from the recursive renderer"
        );
    }
}
