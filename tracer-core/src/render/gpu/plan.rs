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
    let mut groups: Vec<Vec<DispatchParams>> = vec![Vec::new()];
    let mut in_group = 0u64;
    let mut row0 = 0;
    while row0 < rect.height {
        let band = rows.min(rect.height - row0);
        let mut s = samples.start;
        while s < samples.end {
            let e = (s as u64 + chunk).min(samples.end as u64) as u32;
            let work = w * band as u64 * (e - s) as u64;
            let last = groups.last_mut().expect("never empty");
            if !last.is_empty()
                && (in_group + work > o.submit_pixel_samples || last.len() == PARAMS_SLOTS)
            {
                groups.push(Vec::new());
                in_group = 0;
            }
            groups
                .last_mut()
                .expect("never empty")
                .push(DispatchParams {
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
            in_group += work;
            s = e;
        }
        row0 += band;
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
}
