//! Line plots as PNG and SVG (plotters). The font is embedded so plots look
//! the same on machines without any installed fonts.
//!
//! Ticks are chosen here, not by plotters: its log axes put a label at
//! every 0.1, 0.2, ... 0.9 and twice at powers of ten, and their labels ran
//! into each other (`samples/error_vs_time.png`). [`choose_ticks`] takes
//! the densest 1-2-5 set whose labels, at their widest, leave a gap.

use std::ops::Range;
use std::path::Path;
use std::sync::Once;

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint, Ranged};
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is compiled in; a failure here is a build defect.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

pub struct LinePlot {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub log_y: bool,
    pub series: Vec<Series>,
}

const SIZE: (u32, u32) = (900, 600);
/// Margin, label areas and fonts of the chart; the room for tick labels
/// below follows from them.
const MARGIN: u32 = 15;
const X_LABEL_AREA: u32 = 45;
const Y_LABEL_AREA: u32 = 70;
const CAPTION_FONT: u32 = 22;
const LABEL_FONT: u32 = 14;
/// Widest character of the label font at [`LABEL_FONT`] (DejaVu Sans
/// digits are 0.64 em, 'e' 0.62, '.' and '-' less), and the least gap
/// between neighbouring labels, in pixels.
const CHAR_WIDTH: f64 = 0.66 * LABEL_FONT as f64;
const LABEL_GAP: f64 = 12.0;
/// Most labels on one axis.
const MAX_TICKS: usize = 12;

/// Tick labels of one axis, all in one style: plain decimals where every
/// tick allows it (0.05, 0.1, 2, 1500), else short scientific (5e-4, 1e6).
pub fn tick_labels(ticks: &[f64]) -> Vec<String> {
    let plain = ticks
        .iter()
        .all(|&v| v == 0.0 || (1e-3..1e6).contains(&v.abs()));
    ticks
        .iter()
        .map(|&v| {
            if plain {
                let s = format!("{v:.6}");
                let s = s.trim_end_matches('0').trim_end_matches('.');
                if s == "-0" { "0" } else { s }.to_string()
            } else {
                format!("{v:e}")
            }
        })
        .collect()
}

/// `m` x 10^`e` as the nearest f64 to that decimal (no `powi` rounding),
/// so that labels print short.
fn decimal(m: i64, e: i32) -> f64 {
    format!("{m}e{e}").parse().expect("a decimal number")
}

/// Candidate tick sets for lo..hi, densest first: on a log axis 1-2-5,
/// 1-3 and 1 times each power of ten, then every 2nd, 3rd... power; then
/// (on any axis) multiples of 1, 2 and 5 x 10^k.
fn tick_candidates(lo: f64, hi: f64, log: bool) -> Vec<Vec<f64>> {
    let mut out: Vec<Vec<f64>> = Vec::new();
    let within = |v: &f64| (lo..=hi).contains(v);
    if log && lo > 0.0 {
        let (e0, e1) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
        for mantissas in [&[1, 2, 5][..], &[1, 3], &[1]] {
            out.push(
                (e0..=e1)
                    .flat_map(|e| mantissas.iter().map(move |&m| decimal(m, e)))
                    .filter(within)
                    .collect(),
            );
        }
        for every in 2..=(e1 - e0).max(2) {
            out.push(
                (e0..=e1)
                    .filter(|e| e.rem_euclid(every) == 0)
                    .map(|e| decimal(1, e))
                    .filter(within)
                    .collect(),
            );
        }
    }
    let span = hi - lo;
    if span > 0.0 && span.is_finite() {
        let k0 = (span / 50.0).log10().floor() as i32;
        for k in k0..k0 + 4 {
            for m in [1, 2, 5] {
                let step = decimal(m, k);
                let (first, last) = ((lo / step).ceil() as i64, (hi / step).floor() as i64);
                if last - first > 60 {
                    continue;
                }
                out.push(
                    (first..=last)
                        .map(|i| decimal(i * m, k))
                        .filter(|v| !log || *v > 0.0)
                        .filter(within)
                        .collect(),
                );
            }
        }
    }
    // One label says nothing about the scale.
    out.retain(|t| t.len() >= 2);
    out
}

/// Where `ticks` fall along an axis of `len` pixels over lo..hi.
fn positions(ticks: &[f64], lo: f64, hi: f64, log: bool, len: f64) -> Vec<f64> {
    let f = |v: f64| if log { v.ln() } else { v };
    ticks
        .iter()
        .map(|&v| len * (f(v) - f(lo)) / (f(hi) - f(lo)))
        .collect()
}

/// Whether labels at `ticks` leave [`LABEL_GAP`] between each other: on
/// the x axis by their widths (at most [`CHAR_WIDTH`] a character), on the
/// y axis by their height.
pub fn labels_fit(ticks: &[f64], lo: f64, hi: f64, log: bool, len: f64, horizontal: bool) -> bool {
    let labels = tick_labels(ticks);
    let pos = positions(ticks, lo, hi, log, len);
    let extent = |l: &String| {
        if horizontal {
            l.chars().count() as f64 * CHAR_WIDTH
        } else {
            f64::from(LABEL_FONT)
        }
    };
    (1..ticks.len()).all(|i| {
        pos[i] - pos[i - 1] >= (extent(&labels[i]) + extent(&labels[i - 1])) / 2.0 + LABEL_GAP
    })
}

/// The first candidate over lo..hi (the densest of its kind first) whose
/// labels leave room between each other on an axis of `len` pixels, with
/// at most [`MAX_TICKS`] and at least three labels if any set has them
/// (a log axis of less than a decade gets plain steps); the two ends when
/// no set fits.
pub fn choose_ticks(lo: f64, hi: f64, log: bool, len: f64, horizontal: bool) -> Vec<f64> {
    let fitting: Vec<Vec<f64>> = tick_candidates(lo, hi, log)
        .into_iter()
        .filter(|t| t.len() <= MAX_TICKS && labels_fit(t, lo, hi, log, len, horizontal))
        .collect();
    fitting
        .iter()
        .find(|t| t.len() >= 3)
        .or(fitting.first())
        .cloned()
        .unwrap_or_else(|| vec![lo, hi])
}

/// The light grid of a log axis: 1..9 times each power of ten inside.
fn log_grid(lo: f64, hi: f64) -> Vec<f64> {
    let (e0, e1) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
    (e0..=e1)
        .flat_map(|e| (1..10).map(move |m| decimal(m, e)))
        .filter(|v| (lo..=hi).contains(v))
        .collect()
}

/// A linear or a log axis (a closed set: one chart type serves all four
/// combinations).
enum Scale {
    Linear(RangedCoordf64),
    Log(LogCoord<f64>),
}

/// An axis with the ticks chosen by [`choose_ticks`] (labelled, bold grid
/// lines) and the light grid lines.
struct Axis {
    scale: Scale,
    ticks: Vec<f64>,
    grid: Vec<f64>,
}

impl Axis {
    fn new(lo: f64, hi: f64, log: bool, len: f64, horizontal: bool) -> Axis {
        let ticks = choose_ticks(lo, hi, log, len, horizontal);
        let (scale, grid) = if log {
            (Scale::Log((lo..hi).log_scale().into()), log_grid(lo, hi))
        } else {
            (Scale::Linear((lo..hi).into()), ticks.clone())
        };
        Axis { scale, ticks, grid }
    }
}

impl Ranged for Axis {
    type ValueType = f64;
    // The chart's label formatters print the labels ([`tick_labels`]).
    type FormatOption = DefaultFormatting;
    fn range(&self) -> Range<f64> {
        match &self.scale {
            Scale::Linear(c) => c.range(),
            Scale::Log(c) => c.range(),
        }
    }
    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        match &self.scale {
            Scale::Linear(c) => c.map(value, limit),
            Scale::Log(c) => c.map(value, limit),
        }
    }
    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.grid.clone()
        } else {
            self.ticks.clone()
        }
    }
    fn axis_pixel_range(&self, limit: (i32, i32)) -> Range<i32> {
        match &self.scale {
            Scale::Linear(c) => c.axis_pixel_range(limit),
            Scale::Log(c) => c.axis_pixel_range(limit),
        }
    }
}

impl LinePlot {
    /// Writes `STEM.png` and `STEM.svg`.
    pub fn write(&self, stem: &Path) -> Result<()> {
        register_font();
        if self.series.iter().all(|s| s.points.is_empty()) {
            return Ok(());
        }
        if let Some(dir) = stem.parent() {
            std::fs::create_dir_all(dir)
                .map_err(|e| anyhow!("cannot create {}: {e}", dir.display()))?;
        }
        let mut buf = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut buf, SIZE).into_drawing_area();
            self.draw(&root)?;
            root.present().map_err(|e| anyhow!("plot: {e}"))?;
        }
        let png = stem.with_extension("png");
        tracer_core::film::image::write_png(&png, SIZE.0, SIZE.1, &buf)?;
        let svg = stem.with_extension("svg");
        let root = SVGBackend::new(&svg, SIZE).into_drawing_area();
        self.draw(&root)?;
        root.present().map_err(|e| anyhow!("plot: {e}"))?;
        Ok(())
    }

    fn bounds(&self) -> ((f64, f64), (f64, f64)) {
        let pts = self
            .series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| p.0.is_finite() && p.1.is_finite());
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in pts {
            if (self.log_x && x <= 0.0) || (self.log_y && y <= 0.0) {
                continue;
            }
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        let pad = |lo: f64, hi: f64, log: bool| {
            if log {
                (lo / 1.3, hi * 1.3)
            } else {
                let d = (hi - lo).max(hi.abs() * 0.1).max(1e-9);
                (
                    (lo - 0.05 * d).min(if lo >= 0.0 { 0.0 } else { lo }),
                    hi + 0.05 * d,
                )
            }
        };
        (pad(x0, x1, self.log_x), pad(y0, y1, self.log_y))
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<()> {
        let err = |e: &dyn std::fmt::Display| anyhow!("plot {}: {e}", self.title);
        root.fill(&WHITE).map_err(|e| err(&e))?;
        let ((x0, x1), (y0, y1)) = self.bounds();
        // The plotting area: the image less margins, label areas and the
        // caption (its font's height and the margin below it).
        let width = f64::from(SIZE.0 - 2 * MARGIN - Y_LABEL_AREA);
        let height = f64::from(SIZE.1 - 3 * MARGIN - X_LABEL_AREA - CAPTION_FONT);
        let x = Axis::new(x0, x1, self.log_x, width, true);
        let y = Axis::new(y0, y1, self.log_y, height, false);
        let labels = |a: &Axis| (a.ticks.clone(), tick_labels(&a.ticks));
        let ((xt, xl), (yt, yl)) = (labels(&x), labels(&y));
        let label_of = |ticks: &[f64], labels: &[String], v: f64| {
            ticks
                .iter()
                .position(|&t| t == v)
                .map_or_else(String::new, |i| labels[i].clone())
        };
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, ("sans-serif", CAPTION_FONT))
            .margin(MARGIN)
            .x_label_area_size(X_LABEL_AREA)
            .y_label_area_size(Y_LABEL_AREA)
            .build_cartesian_2d(x, y)
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc(&self.x_label)
            .y_desc(&self.y_label)
            .x_label_formatter(&|v| label_of(&xt, &xl, *v))
            .y_label_formatter(&|v| label_of(&yt, &yl, *v))
            .label_style(("sans-serif", LABEL_FONT))
            .draw()
            .map_err(|e| err(&e))?;
        for (i, s) in self.series.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            let pts: Vec<(f64, f64)> = s
                .points
                .iter()
                .copied()
                .filter(|p| p.0.is_finite() && p.1.is_finite())
                .collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
                .map_err(|e| err(&e))?
                .label(&s.name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            chart
                .draw_series(pts.into_iter().map(|p| Circle::new(p, 4, colour.filled())))
                .map_err(|e| err(&e))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", LABEL_FONT))
            .draw()
            .map_err(|e| err(&e))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const WIDTH: f64 = (SIZE.0 - 2 * MARGIN - Y_LABEL_AREA) as f64;
    const HEIGHT: f64 = (SIZE.1 - 3 * MARGIN - X_LABEL_AREA - CAPTION_FONT) as f64;

    /// The axes of the committed figures (docs/bench/*) and wider ones:
    /// every x axis keeps its labels apart, every y axis too, with at least
    /// three labels and plain numbers where they fit.
    #[test]
    fn labels_never_overlap_on_any_axis() {
        let axes: [(f64, f64, bool); 13] = [
            // samples/error_vs_time, 2 cores (where x labels overlapped) and the H200
            (0.05 / 1.3, 1.9 * 1.3, true),
            (0.004 / 1.3, 0.45 * 1.3, true),
            (0.0006 / 1.3, 0.0105 * 1.3, true),
            // seven decades, and more
            (1e-4, 1e3, true),
            (1e-9, 1e9, true),
            // under one decade: launch/glass-9_gpu_time's y axis (ms)
            (0.31, 0.47, true),
            (380.0, 1100.0, true),
            // linear: megapixels, workers, depth, wide integers, negatives
            (0.0, 2.2, false),
            (0.6, 8.4, false),
            (0.0, 12.6, false),
            (0.0, 123_456_789.0, false),
            (-3.5, 2.5, false),
            (0.000_12, 0.000_19, false),
        ];
        for (lo, hi, log) in axes {
            for (len, horizontal) in [(WIDTH, true), (HEIGHT, false)] {
                let t = choose_ticks(lo, hi, log, len, horizontal);
                let labels = tick_labels(&t);
                assert!(
                    t.len() >= 3 && labels_fit(&t, lo, hi, log, len, horizontal),
                    "{lo}..{hi} log {log} horizontal {horizontal}: {labels:?}"
                );
                assert!(t.windows(2).all(|w| w[0] < w[1]), "{t:?}");
                assert!(t.iter().all(|v| (lo..=hi).contains(v)), "{t:?}");
                // No label printed twice (plotters wrote 0.01 twice).
                let mut l = labels.clone();
                l.dedup();
                assert_eq!(l, labels);
            }
        }
        // What the 2-core error_vs_time now shows on x and y.
        assert_eq!(
            tick_labels(&choose_ticks(0.05 / 1.3, 1.9 * 1.3, true, WIDTH, true)),
            ["0.05", "0.1", "0.2", "0.5", "1", "2"]
        );
        assert_eq!(
            tick_labels(&choose_ticks(
                0.0006 / 1.3,
                0.0105 * 1.3,
                true,
                HEIGHT,
                false
            )),
            // 0.0005 would be plain; one style an axis: all scientific.
            ["5e-4", "1e-3", "2e-3", "5e-3", "1e-2"]
        );
        assert_eq!(
            tick_labels(&choose_ticks(1e-9, 1e9, true, WIDTH, true)),
            [
                "1e-8", "1e-6", "1e-4", "1e-2", "1e0", "1e2", "1e4", "1e6", "1e8"
            ]
        );
    }
}
