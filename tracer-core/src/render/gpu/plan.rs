//! Splitting a render into dispatches and submissions of bounded size.

use super::layout::DispatchParams;
use super::{GpuOptions, PARAMS_SLOTS};
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
                chunk: 0,
            });
            s = e;
        }
        row0 += band;
    }
    group(dispatches, o)
}

/// Samples one invocation of a listed dispatch traces (sums.wgsl
/// `listed_work`), summed in registers before its pixel's atomic
/// additions: a quarter of the additions to the film, spread over fewer
/// invocations of each pixel at once.
pub(super) const LISTED_CHUNK: u32 = 4;

/// A listed dispatch's slices: items a slice within the dispatch budget
/// (64 pixels by `LISTED_CHUNK` samples an item).
pub(super) fn slice_items(o: GpuOptions) -> u32 {
    (o.dispatch_pixel_samples / (64 * LISTED_CHUNK as u64)).clamp(1, 1 << 24) as u32
}

/// Workgroups (x, y) of `group` invocations for `items` listed items (64
/// invocations each), x at most 65535. allocate.wgsl computes the same
/// for its indirect arguments.
pub(super) fn listed_groups(items: u32, group: u32) -> (u32, u32) {
    let groups = (items as u64 * 64).div_ceil(group as u64) as u32;
    let x = groups.min(65_535);
    (x, if x == 0 { 0 } else { groups.div_ceil(x) })
}

/// A listed grid's dispatches (`rect`: 8 grid rows a listed block; each
/// block its own range, `items` in all): slices of at most
/// [`slice_items`] items, each flagged `ranged`, in bounded submissions.
pub(super) fn plan_listed(
    rect: Rect,
    film: (u32, u32),
    items: u32,
    frame: u32,
    o: GpuOptions,
) -> Vec<Vec<DispatchParams>> {
    let per = slice_items(o);
    let dispatches = (0..items.div_ceil(per))
        .map(|s| listed_slice(rect, film, frame, s * per, ((s + 1) * per).min(items)))
        .collect();
    group(dispatches, o)
}

/// The dispatch of items `start..end` of a listed grid.
pub(super) fn listed_slice(
    rect: Rect,
    film: (u32, u32),
    frame: u32,
    start: u32,
    end: u32,
) -> DispatchParams {
    DispatchParams {
        rect_x: rect.x,
        rect_y: rect.y,
        rect_w: rect.width,
        rect_h: rect.height,
        row0: 0,
        rows: 0,
        sample_start: start,
        sample_end: end,
        frame,
        film_w: film.0,
        film_h: film.1,
        ranged: 1,
        chunk: LISTED_CHUNK,
    }
}

/// Pixel-samples dispatch `d` traces at most: a listed one's items whole.
pub(super) fn dispatch_work(d: &DispatchParams) -> u64 {
    let n = (d.sample_end - d.sample_start) as u64;
    if d.ranged != 0 {
        n * 64 * d.chunk as u64
    } else {
        d.rect_w as u64 * d.rows as u64 * n
    }
}

/// Dispatches in order, grouped into submissions of at most
/// `submit_pixel_samples` (a larger dispatch alone) and [`PARAMS_SLOTS`].
fn group(dispatches: Vec<DispatchParams>, o: GpuOptions) -> Vec<Vec<DispatchParams>> {
    let mut groups: Vec<Vec<DispatchParams>> = vec![Vec::new()];
    let mut in_group = 0u64;
    for d in dispatches {
        let work = dispatch_work(&d);
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
    use crate::adaptive::BLOCK;
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
    fn listed_slices_cover_the_items_once_within_budgets() {
        let o = GpuOptions {
            workgroup: (8, 4),
            dispatch_pixel_samples: 64 * LISTED_CHUNK as u64 * 10,
            submit_pixel_samples: 64 * LISTED_CHUNK as u64 * 25,
            strategy: Strategy::Stack,
        };
        let rect = Rect::new(5, 9, BLOCK, BLOCK * 7);
        let groups = plan_listed(rect, (64, 48), 93, 3, o);
        let mut next = 0;
        for g in &groups {
            assert!(g.len() <= PARAMS_SLOTS);
            assert!(g.iter().map(dispatch_work).sum::<u64>() <= o.submit_pixel_samples);
            for d in g {
                assert_eq!(
                    (d.rect_x, d.rect_h, d.ranged, d.frame),
                    (5, rect.height, 1, 3)
                );
                assert_eq!(d.sample_start, next);
                assert!(d.sample_end - d.sample_start <= 10);
                next = d.sample_end;
                // Enough 32-invocation workgroups for 64 invocations an item.
                let (x, y) = listed_groups(d.sample_end - d.sample_start, 32);
                assert!(x * y * 32 >= 64 * (d.sample_end - d.sample_start));
            }
        }
        assert_eq!(next, 93);
        assert_eq!(listed_groups(0, 64), (0, 0));
        assert_eq!(listed_groups(70_000, 64), (65_535, 2));
    }
}
