//! What one render's dispatch grid covers: the film, or an adaptive
//! render's listed blocks (8 columns, 8 rows a block: sums.wgsl
//! `grid_pixel`), each over the render's samples or its own range (a
//! listed grid: sums.wgsl `listed_work`).

use wgpu::util::DeviceExt as _;

use super::Readout;
use super::layout::{ADAPTIVE_SUM_WORDS, DispatchParams, GpuBlockStats, SUM_WORDS};
use super::plan::LISTED_CHUNK;
use crate::adaptive::{BLOCK, BlockMask};
use crate::film::{Film, Rect, RunCost};

pub(super) struct Grid<'a> {
    /// The film's rect.
    pub film: Rect,
    /// An adaptive render's blocks (those listed are the active ones).
    pub mask: Option<&'a BlockMask>,
    /// The listed blocks, each column | row << 16.
    blocks: Vec<u32>,
    /// A ranged render's (first, end, first item, 0) per listed block,
    /// and an entry with the items in all ([`listed`]).
    ranges: Option<Vec<[u32; 4]>>,
    pub blocks_buffer: Option<wgpu::Buffer>,
    pub ranges_buffer: Option<wgpu::Buffer>,
    /// A ranged render's rays per listed block, (low, high) words, zeroed:
    /// the trace kernel's `block_rays`.
    pub rays_buffer: Option<wgpu::Buffer>,
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
            // Every block, the first round's range (the GPU writes the
            // later rounds', allocate.wgsl).
            Readout::Rmse(r) => r.rounds.borrow().pending_ranges(),
            _ => None,
        }
        .map(|r| listed(&r));
        let storage = |label, contents: &[u8]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_DST
                    | wgpu::BufferUsages::COPY_SRC,
            })
        };
        Grid {
            film,
            mask,
            blocks_buffer: mask.map(|_| storage("active blocks", bytemuck::cast_slice(&blocks))),
            ranges_buffer: ranges
                .as_ref()
                .map(|r| storage("block ranges", bytemuck::cast_slice(r))),
            rays_buffer: ranges
                .as_ref()
                .map(|r| storage("block rays", bytemuck::cast_slice(&vec![0u32; 2 * r.len()]))),
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

    /// A ranged render's cost of each listed block, from the words of its
    /// [`Grid::rays_buffer`]: one run a block, its rays and the samples
    /// each of its pixels took (the film's `runs`, as a CPU's round
    /// books them, there by runs of blocks).
    pub fn runs(&self, rays: &[u32]) -> Vec<RunCost> {
        let (Some(m), Some(rs)) = (self.mask, &self.ranges) else {
            return Vec::new();
        };
        self.blocks
            .iter()
            .zip(rs)
            .zip(rays.chunks_exact(2))
            .map(|((&b, r), w)| RunCost {
                rect: m.block_rect(listed_index(m, b)),
                rays: w[0] as u64 | (w[1] as u64) << 32,
                samples: r[1] - r[0],
            })
            .collect()
    }

    /// A listed grid's items in all.
    pub fn items(&self) -> Option<u32> {
        self.ranges.as_ref().map(|r| r[r.len() - 1][2])
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
        let pixels = |b: u32| {
            let (fx, fy) = ((b & 0xffff) * BLOCK, (b >> 16) * BLOCK);
            (film.width.saturating_sub(fx).min(BLOCK) * film.height.saturating_sub(fy).min(BLOCK))
                as u64
        };
        match (self.mask, &self.ranges) {
            (None, _) => film.width as u64 * d.rows as u64 * n,
            // The items of the listed blocks the dispatch's items overlap
            // (from the last block starting at or before its first), as
            // samples.
            (Some(_), Some(rs)) => (rs[..self.blocks.len()]
                .partition_point(|r| r[2] <= d.sample_start)
                .saturating_sub(1)..self.blocks.len())
                .take_while(|&k| rs[k][2] < d.sample_end)
                .map(|k| {
                    let [first, end, item, _] = rs[k];
                    let (a, b) = (d.sample_start.max(item), d.sample_end.min(rs[k + 1][2]));
                    if a >= b {
                        return 0;
                    }
                    let from = first + (a - item) * d.chunk;
                    let to = (first + (b - item) * d.chunk).min(end);
                    pixels(self.blocks[k]) * (to - from) as u64
                })
                .sum(),
            (Some(_), None) => (d.row0..d.row0 + d.rows)
                .map(|r| {
                    let b = self.blocks[(r / BLOCK) as usize];
                    let (fx, fy) = ((b & 0xffff) * BLOCK, (b >> 16) * BLOCK + r % BLOCK);
                    if fy < film.height {
                        (film.width - fx).min(BLOCK) as u64 * n
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
        for (k, &b) in self.blocks.iter().enumerate() {
            let n = match &self.ranges {
                Some(rs) => rs[k][1] - rs[k][0],
                None => samples,
            };
            fill(m.block_rect(listed_index(m, b)), n);
        }
    }
}

/// The index in `m` of a listed block (column | row << 16).
fn listed_index(m: &BlockMask, b: u32) -> usize {
    ((b >> 16) * m.cols() + (b & 0xffff)) as usize
}

/// Listed blocks' ranges (first, end) as the trace kernel reads them:
/// (first, end, first item, 0), each block [`LISTED_CHUNK`] samples an
/// item, then an entry whose third word is the items in all.
pub fn listed(ranges: &[[u32; 2]]) -> Vec<[u32; 4]> {
    let mut item = 0;
    let mut out: Vec<[u32; 4]> = ranges
        .iter()
        .map(|&[a, b]| {
            let first = item;
            item += (b - a).div_ceil(LISTED_CHUNK);
            [a, b, first, 0]
        })
        .collect();
    out.push([0, 0, item, 0]);
    out
}
