//! Every example scene: golden images, f32 against the f64 reference, and
//! exact additivity of tiles and sample ranges.
//!
//! Golden images live in `tests/golden/` as 8-bit sRGB PNGs. To re-bless
//! them after an intended change to the images, run
//! `TESSERA_BLESS=1 cargo test -p tracer-core --test examples` and look at
//! the new files before committing them.

mod common;

use std::path::{Path, PathBuf};
use tracer_core::film::WorkRegion;

use common::*;
use tracer_core::film::{Film, Rect, SampleRange, to_srgb8};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};

/// Small enough to keep the suite quick, large enough to show every object.
const W: u32 = 160;
const H: u32 = 120;

fn example_scenes() -> Vec<PathBuf> {
    let dir = examples_dir();
    let mut out = vec![];
    for d in [dir.clone(), dir.join("complexity")] {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "toml") {
                out.push(p);
            }
        }
    }
    out.sort();
    assert!(
        out.len() >= 19,
        "expected the thesis scenes and the showcase, found {out:?}"
    );
    out
}

fn small(desc: &SceneDesc) -> RenderSettings {
    RenderSettings {
        width: W,
        height: H,
        ..desc.render
    }
}

fn golden_name(path: &Path) -> String {
    let rel = path.strip_prefix(examples_dir()).unwrap();
    rel.with_extension("png")
        .to_string_lossy()
        .replace(['/', '\\'], "-")
}

#[test]
fn example_scenes_match_their_golden_images() {
    let mut failures = vec![];
    for path in example_scenes() {
        let desc = SceneDesc::load(&path).unwrap();
        let film = render_with(&desc, &small(&desc), Precision::F32);
        let got = to_srgb8(&film.resolve());
        if let Err(e) = check_golden(&golden_name(&path), W, H, got, 1) {
            failures.push(format!("{}: {e}", path.display()));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn f32_matches_the_f64_reference_on_every_example() {
    for path in example_scenes() {
        let desc = SceneDesc::load(&path).unwrap();
        let s = small(&desc);
        let a = render_with(&desc, &s, Precision::F32).resolve();
        let b = render_with(&desc, &s, Precision::F64).resolve();
        // f32 rounding moves each hit by ~1e-7 relative; after up to 10
        // generations of reflection/refraction a sample near a silhouette may
        // see a different object. Stated tolerance: mean absolute difference
        // below 1/1000, and at most 1% of pixels off by more than 2/255.
        let d = diff(&a, &b, 2.0 / 255.0);
        assert!(
            d.mean < 1e-3,
            "{}: mean f32/f64 difference {}",
            path.display(),
            d.mean
        );
        assert!(
            d.over * 100 <= d.pixels,
            "{}: {} of {} pixels differ by > 2/255",
            path.display(),
            d.over,
            d.pixels
        );
    }
}

#[test]
fn tiles_and_sample_ranges_add_up_to_the_whole_render_exactly() {
    let desc = SceneDesc::load(examples_dir().join("resolution.toml")).unwrap();
    for (sampler, samples) in [("grid", 9), ("jittered", 9), ("jittered", 5)] {
        let settings = RenderSettings {
            width: 67,
            height: 41,
            samples,
            sampler: sampler.parse().unwrap(),
            ..desc.render
        };
        for precision in [Precision::F32, Precision::F64] {
            let frame = PreparedFrame::build(&desc, &settings, 3, precision).unwrap();
            let whole = CpuRenderer::new(Some(2))
                .unwrap()
                .render(
                    &frame,
                    WorkRegion::new(3, Rect::full(67, 41), SampleRange::all(samples)),
                    &|_| {},
                )
                .unwrap();
            // Uneven tiles x uneven sample batches, merged in a scrambled order, on one thread.
            let one = CpuRenderer::new(Some(1)).unwrap();
            let mut parts = vec![];
            for rect in [
                Rect::new(0, 0, 30, 41),
                Rect::new(30, 0, 37, 17),
                Rect::new(30, 17, 37, 24),
            ] {
                for range in [
                    SampleRange::new(0, 2),
                    SampleRange::new(2, 3),
                    SampleRange::new(3, samples),
                ] {
                    parts.push(
                        one.render(&frame, WorkRegion::new(3, rect, range), &|_| {})
                            .unwrap(),
                    );
                }
            }
            let mut merged = Film::new(Rect::full(67, 41));
            for i in [4, 0, 8, 2, 6, 1, 7, 3, 5] {
                merged.merge(&parts[i]).unwrap();
            }
            assert_eq!(
                merged.sums, whole.sums,
                "{sampler} {samples} {precision:?}: sums differ"
            );
            assert_eq!(merged.counts, whole.counts);
            assert_eq!(merged.rays, whole.rays);
        }
    }
}

/// A small frame on many threads is rendered in slices of its samples
/// (`render::cpu`'s pieces): the film must be its tiles rendered whole.
#[test]
fn renders_cut_into_sample_slices_are_their_tiles_rendered_whole() {
    use tracer_core::render::cpu::{TILE, render_tile};
    for (scene, sampler) in [
        ("resolution.toml", "jittered"),
        ("distributed.toml", "grid"),
    ] {
        let desc = SceneDesc::load(examples_dir().join(scene)).unwrap();
        let settings = RenderSettings {
            width: 67,
            height: 41,
            samples: 9,
            sampler: sampler.parse().unwrap(),
            ..desc.render
        };
        let rect = Rect::full(67, 41);
        for precision in [Precision::F32, Precision::F64] {
            let frame = PreparedFrame::build(&desc, &settings, 2, precision).unwrap();
            let mut whole = Film::new(rect);
            for tile in rect.tiles(TILE) {
                let film = match &frame {
                    PreparedFrame::F32(w) => render_tile(w, 2, tile, SampleRange::all(9)),
                    PreparedFrame::F64(w) => render_tile(w, 2, tile, SampleRange::all(9)),
                };
                whole.merge(&film).unwrap();
            }
            // 15 tiles: one thread takes 3 slices of each, 64 threads 9.
            for threads in [1, 2, 64] {
                let film = CpuRenderer::new(Some(threads))
                    .unwrap()
                    .render(
                        &frame,
                        WorkRegion::new(2, rect, SampleRange::all(9)),
                        &|_| {},
                    )
                    .unwrap();
                let case = format!("{scene} {precision:?} on {threads} threads");
                assert_eq!(film.sums, whole.sums, "{case}: sums differ");
                assert_eq!(film.counts, whole.counts, "{case}");
                assert_eq!(film.rays, whole.rays, "{case}");
            }
        }
    }
}

#[test]
fn render_requests_outside_the_image_are_refused() {
    let desc = SceneDesc::load(examples_dir().join("resolution.toml")).unwrap();
    let s = RenderSettings {
        width: 16,
        height: 16,
        samples: 4,
        ..desc.render
    };
    let frame = PreparedFrame::build(&desc, &s, 0, Precision::F32).unwrap();
    let r = CpuRenderer::new(Some(1)).unwrap();
    assert_bad_regions_refused(|rect, samples| {
        r.render(&frame, WorkRegion::new(0, rect, samples), &|_| {})
            .unwrap_err()
            .to_string()
    });
}
