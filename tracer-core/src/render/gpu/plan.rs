//! Splitting a render into dispatches and submissions of bounded size.

use super::layout::DispatchParams;
use super::{GpuOptions, PARAMS_SLOTS};
use crate::adaptive::BLOCK;
use crate::film::{Rect, SampleRange};

/// Splits a render into dispatches (bands of rows x ranges of samples, each
/// at most `dispatch_pixel_samples`), grouped into submissions of at most
/// `submit_pixel_samples` and [`PARAMS_SLOTS`] dispatches.
/// `rect` is the grid (the film, or an adaptive round's blocks) and
/// `film` the film's size.
pub(super) fn plan(
    rect: Rect,
    film: (u32, u32),
    samples: SampleRange,
    frame: u32,
    o: GpuOptions,
) -> Vec<Vec<DispatchParams>> {
    let w = rect.width as u64;
    let len = samples.len() as u64;
    let budget = o.dispatch_pixel_samples.max(1);
    // Samples are a dispatch's z dimension: at most 65535 workgroups.
    let chunk = (budget / w).clamp(1, len).min(65_535);
    let rows = (budget / (w * chunk)).clamp(1, rect.height as u64) as u32;
    let mut dispatches = Vec::new();
    let mut row0 = 0;
    while row0 < rect.height {
        let band = rows.min(rect.height - row0);
        let mut s = samples.start;
        while s < samples.end {
            let e = (s as u64 + chunk).min(samples.end as u64) as u32;
            dispatches.push(DispatchParams {
                rect_x: rect.x,
                rect_y: rect.y,
                rect_w: rect.width,
                rect_h: rect.height,
                row0,
                rows: band,
                sample_start: s,
                sample_end: e,
                frame,
                film_w: film.0,
                film_h: film.1,
                ranged: 0,
            });
            s = e;
        }
        row0 += band;
    }
    group(dispatches, o)
}

/// A ranged grid's dispatches (`rect`: 8 grid rows a listed block),
/// `lengths` being each listed block's range length in the grid's order,
/// longest first. The blocks go in bands whose lengths are within a
/// factor of 2, each dispatched over its longest range's samples, so that
/// threads past their own block's range (which return at once) are at
/// most half of a band's, rather than most of the grid's when a few
/// blocks take many more samples than the rest; blocks with nothing to
/// render get no dispatch. Each dispatch flagged `ranged`.
pub(super) fn plan_bands(
    rect: Rect,
    film: (u32, u32),
    lengths: &[u32],
    frame: u32,
    o: GpuOptions,
) -> Vec<Vec<DispatchParams>> {
    let mut dispatches = Vec::new();
    let mut b = 0;
    while b < lengths.len() && lengths[b] > 0 {
        let longest = lengths[b];
        let mut e = b + 1;
        while e < lengths.len() && 2 * lengths[e] > longest {
            e += 1;
        }
        let band = Rect::new(rect.x, rect.y, rect.width, BLOCK * (e - b) as u32);
        for group in plan(band, film, SampleRange::new(0, longest), frame, o) {
            for mut d in group {
                d.row0 += BLOCK * b as u32;
                d.rect_h = rect.height;
                d.ranged = 1;
                dispatches.push(d);
            }
        }
        b = e;
    }
    group(dispatches, o)
}

/// Dispatches in order, grouped into submissions of at most
/// `submit_pixel_samples` (a larger dispatch alone) and [`PARAMS_SLOTS`].
fn group(dispatches: Vec<DispatchParams>, o: GpuOptions) -> Vec<Vec<DispatchParams>> {
    let mut groups: Vec<Vec<DispatchParams>> = vec![Vec::new()];
    let mut in_group = 0u64;
    for d in dispatches {
        let work = d.rect_w as u64 * d.rows as u64 * (d.sample_end - d.sample_start) as u64;
        let last = groups.last_mut().expect("never empty");
        if !last.is_empty()
            && (in_group + work > o.submit_pixel_samples || last.len() == PARAMS_SLOTS)
        {
            groups.push(Vec::new());
            in_group = 0;
        }
        groups.last_mut().expect("never empty").push(d);
        in_group += work;
    }
    groups
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::gpu::Strategy;

    #[test]
    fn plan_covers_every_pixel_sample_once_within_budgets() {
        let o = GpuOptions {
            workgroup: (8, 8),
            dispatch_pixel_samples: 1000,
            submit_pixel_samples: 5000,
            strategy: Strategy::Stack,
        };
        let rect = Rect::new(3, 7, 37, 23);
        let samples = SampleRange::new(2, 11);
        let groups = plan(rect, (rect.width, rect.height), samples, 0, o);
        let mut hits = vec![0u32; rect.area() * 16];
        for g in &groups {
            assert!(g.len() <= PARAMS_SLOTS);
            let work: u64 = g
                .iter()
                .map(|d| d.rect_w as u64 * d.rows as u64 * (d.sample_end - d.sample_start) as u64)
                .sum();
            assert!(
                work <= o.submit_pixel_samples || g.len() == 1,
                "group of {work}"
            );
            for d in g {
                for r in d.row0..d.row0 + d.rows {
                    for s in d.sample_start..d.sample_end {
                        for c in 0..d.rect_w {
                            hits[((r * rect.width + c) * 16 + s) as usize] += 1;
                        }
                    }
                }
            }
        }
        for r in 0..rect.height {
            for c in 0..rect.width {
                for s in 0..16 {
                    let want = u32::from((samples.start..samples.end).contains(&s));
                    assert_eq!(hits[((r * rect.width + c) * 16 + s) as usize], want);
                }
            }
        }
        // A row wider than the budget still gets one sample per dispatch.
        let wide = plan(Rect::full(4000, 2), (4000, 2), SampleRange::all(3), 0, o);
        assert_eq!(wide.iter().map(|g| g.len()).sum::<usize>(), 6);
    }

    #[test]
    fn bands_dispatch_each_block_over_its_range_at_most_twice_over() {
        let o = GpuOptions {
            workgroup: (8, 8),
            dispatch_pixel_samples: 700,
            submit_pixel_samples: 3000,
            strategy: Strategy::Stack,
        };
        // Longest first, as a ranged grid lists them; the zeros get nothing.
        let lengths = [40, 33, 21, 20, 11, 3, 2, 1, 0, 0];
        let rect = Rect::new(5, 9, BLOCK, BLOCK * lengths.len() as u32);
        let groups = plan_bands(rect, (64, 48), &lengths, 3, o);
        // Samples offered to each grid row (a thread past its block's
        // range returns at once).
        let mut offered = vec![0u32; rect.height as usize];
        for g in &groups {
            assert!(g.len() <= PARAMS_SLOTS);
            for d in g {
                assert_eq!(
                    (d.rect_x, d.rect_y, d.rect_h, d.ranged),
                    (5, 9, rect.height, 1)
                );
                for r in d.row0..d.row0 + d.rows {
                    offered[r as usize] += d.sample_end - d.sample_start;
                }
            }
        }
        for (b, &len) in lengths.iter().enumerate() {
            for r in 0..BLOCK as usize {
                let got = offered[b * BLOCK as usize + r];
                if len == 0 {
                    assert_eq!(got, 0, "block {b}: nothing to render");
                } else {
                    assert!(got >= len && got < 2 * len, "block {b} ({len}): {got}");
                }
            }
        }
    }
}
