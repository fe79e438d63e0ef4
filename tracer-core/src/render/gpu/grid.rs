//! What one render's dispatch grid covers: the film, or an adaptive
//! render's listed blocks (8 columns, 8 rows a block: sums.wgsl
//! `grid_pixel`), each over the render's samples or its own range.

use wgpu::util::DeviceExt as _;

use super::Readout;
use super::layout::{ADAPTIVE_SUM_WORDS, DispatchParams, GpuBlockStats, SUM_WORDS};
use crate::adaptive::{BLOCK, BlockMask};
use crate::film::{Film, Rect};

pub(super) struct Grid<'a> {
    /// The film's rect.
    pub film: Rect,
    /// An adaptive render's blocks (those listed are the active ones).
    pub mask: Option<&'a BlockMask>,
    /// The listed blocks, each column | row << 16.
    blocks: Vec<u32>,
    /// A ranged render's (first, end) per listed block.
    ranges: Option<Vec<[u32; 2]>>,
    pub blocks_buffer: Option<wgpu::Buffer>,
    pub ranges_buffer: Option<wgpu::Buffer>,
}

impl<'a> Grid<'a> {
    pub fn new(device: &wgpu::Device, readout: Readout<'a>, film: Rect) -> Self {
        let mask = match readout {
            Readout::Adaptive(m) | Readout::Ranged(m, _) => Some(m),
            Readout::Resident(r) => Some(&r.mask),
            Readout::Rmse(r) => Some(&r.mask),
            _ => None,
        };
        let blocks: Vec<u32> = mask.map_or_else(Vec::new, |m| {
            let cols = m.cols() as usize;
            m.active
                .iter()
                .enumerate()
                .filter(|(_, a)| **a)
                .map(|(i, _)| (i % cols) as u32 | ((i / cols) as u32) << 16)
                .collect()
        });
        let ranges = match readout {
            Readout::Ranged(_, r) => Some(
                r.iter()
                    .flatten()
                    .map(|r| [r.start, r.end])
                    .collect::<Vec<[u32; 2]>>(),
            ),
            // Every block, the first round's range (rewritten each round).
            Readout::Rmse(r) => r.rounds.borrow().pending_ranges(),
            _ => None,
        };
        // A ranged grid lists its blocks longest range first, for
        // `plan_bands`: where a block lies is in its entry, so the film's
        // sums are the same in any order.
        let (blocks, ranges) = match ranges {
            Some(r) => {
                let (b, r) = by_length(&blocks, &r);
                (b, Some(r))
            }
            None => (blocks, None),
        };
        let storage = |label, contents: &[u8]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            })
        };
        Grid {
            film,
            mask,
            blocks_buffer: mask.map(|_| storage("active blocks", bytemuck::cast_slice(&blocks))),
            ranges_buffer: ranges
                .as_ref()
                .map(|r| storage("block ranges", bytemuck::cast_slice(r))),
            blocks,
            ranges,
        }
    }

    /// The dispatch grid: the film, or 8 columns by 8 rows a listed block.
    pub fn rect(&self) -> Rect {
        match self.mask {
            Some(_) => Rect::new(
                self.film.x,
                self.film.y,
                BLOCK,
                BLOCK * self.blocks.len() as u32,
            ),
            None => self.film,
        }
    }

    /// A ranged grid's range lengths, in its order (longest first).
    pub fn lengths(&self) -> Option<Vec<u32>> {
        self.ranges
            .as_ref()
            .map(|r| r.iter().map(|[a, b]| b - a).collect())
    }

    /// Every block's range for the next dispatches, in the mask's order
    /// (every block of the mask listed): the grid's lists, reordered
    /// longest first, written to the device's copies behind the work
    /// queued so far.
    pub fn set_ranges(&mut self, queue: &wgpu::Queue, ranges: &[[u32; 2]]) {
        let m = self.mask.expect("a ranged grid");
        let cols = m.cols() as usize;
        let entries: Vec<u32> = (0..ranges.len())
            .map(|i| (i % cols) as u32 | ((i / cols) as u32) << 16)
            .collect();
        let (blocks, ranges) = by_length(&entries, ranges);
        let buffers = self.blocks_buffer.as_ref().zip(self.ranges_buffer.as_ref());
        let (b, r) = buffers.expect("a ranged grid has both lists");
        queue.write_buffer(b, 0, bytemuck::cast_slice(&blocks));
        queue.write_buffer(r, 0, bytemuck::cast_slice(&ranges));
        self.blocks = blocks;
        self.ranges = Some(ranges);
    }

    /// u32 words of a pixel's sums: with sums of squares in an adaptive render.
    pub fn sum_words(&self) -> usize {
        if self.mask.is_some() {
            ADAPTIVE_SUM_WORDS
        } else {
            SUM_WORDS
        }
    }

    /// Pixel-samples dispatch `d` traces: the film's pixels in its band of
    /// the grid's rows (blocks cut by the film's edge hold fewer than
    /// their 64 grid cells) times its samples (in a ranged render, those
    /// of each block's range).
    pub fn work(&self, d: &DispatchParams) -> u64 {
        let n = (d.sample_end - d.sample_start) as u64;
        let film = self.film;
        match self.mask {
            None => film.width as u64 * d.rows as u64 * n,
            Some(_) => (d.row0..d.row0 + d.rows)
                .map(|r| {
                    let b = self.blocks[(r / BLOCK) as usize];
                    let (fx, fy) = ((b & 0xffff) * BLOCK, (b >> 16) * BLOCK + r % BLOCK);
                    let samples = match &self.ranges {
                        Some(rs) => {
                            let [a, e] = rs[(r / BLOCK) as usize];
                            d.sample_end.min(e - a).saturating_sub(d.sample_start) as u64
                        }
                        None => n,
                    };
                    if fy < film.height {
                        (film.width - fx).min(BLOCK) as u64 * samples
                    } else {
                        0
                    }
                })
                .sum(),
        }
    }

    /// Sets each pixel's count of `film` (this grid's film): `samples`
    /// everywhere, or over the listed blocks only, or each listed block its
    /// range's length, or (a resident adaptive render, `stopped`) each
    /// block the samples it stopped at.
    pub fn fill_counts(&self, film: &mut Film, samples: u32, stopped: Option<&[GpuBlockStats]>) {
        let Some(m) = self.mask else {
            film.counts.fill(samples);
            return;
        };
        let rect = self.film;
        let mut fill = |b: Rect, n: u32| {
            for y in b.y..b.y + b.height {
                let row = ((y - rect.y) * rect.width + (b.x - rect.x)) as usize;
                film.counts[row..row + b.width as usize].fill(n);
            }
        };
        if let Some(stats) = stopped {
            for (i, st) in stats.iter().enumerate() {
                fill(m.block_rect(i), st.samples);
            }
            return;
        }
        let cols = m.cols();
        for (k, &b) in self.blocks.iter().enumerate() {
            let n = match &self.ranges {
                Some(rs) => rs[k][1] - rs[k][0],
                None => samples,
            };
            fill(m.block_rect(((b >> 16) * cols + (b & 0xffff)) as usize), n);
        }
    }
}

/// Block entries and their ranges, longest range first (stable: equal
/// lengths keep their order).
fn by_length(blocks: &[u32], ranges: &[[u32; 2]]) -> (Vec<u32>, Vec<[u32; 2]>) {
    let mut order: Vec<usize> = (0..blocks.len()).collect();
    order.sort_by_key(|&k| std::cmp::Reverse(ranges[k][1] - ranges[k][0]));
    order.iter().map(|&k| (blocks[k], ranges[k])).unzip()
}
