//! The CPU renderer: rayon over small tiles. Scenes of spheres and planes
//! in f32 take the stream renderer ([`stream`]), vectorised over rays; the
//! rest (meshes, BVH scenes, the f64 reference) trace with the recursive
//! driver over the one shading step (`step::shade`), camera rays and their shadow rays in
//! packets of 4x4 pixels ([`World::closest_hits`], [`World::occluded_many`])
//! and the rays they spawn one at a time.

pub mod adaptive;
pub mod distributed;
pub mod kernels;
pub mod shade;
pub mod stream;

use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;

use super::step::{Static, Surface};
use super::{PreparedFrame, RenderError};
use crate::film::{Film, RayCounts, Rect, SampleRange, WorkRegion};
use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3};
use crate::sampling::{pixel_seed, sample_offset};
use crate::world::World;

/// Side of the square tiles the threads take in turn: small enough to
/// balance load on a few cores, large enough that scheduling is negligible.
pub const TILE: u32 = 16;

/// Most threads a renderer takes: beyond any machine's cores, so a larger
/// number is a typo (it would only fail later, spawning threads).
pub const MAX_THREADS: usize = 4096;

pub struct CpuRenderer {
    pool: rayon::ThreadPool,
}

pub use stream::SimdLevel;

impl CpuRenderer {
    /// `threads`: `None` uses every core.
    pub fn new(threads: Option<usize>) -> Result<Self, RenderError> {
        let mut b = rayon::ThreadPoolBuilder::new().thread_name(|i| format!("tessera-cpu-{i}"));
        // 0, like None, means every core (rayon's default).
        if let Some(n) = threads.filter(|&n| n > 0) {
            if n > MAX_THREADS {
                return Err(RenderError::Threads(format!(
                    "{n} threads asked for; at most {MAX_THREADS}"
                )));
            }
            b = b.num_threads(n);
        }
        Ok(CpuRenderer {
            pool: b.build().map_err(|e| RenderError::Threads(e.to_string()))?,
        })
    }

    pub fn threads(&self) -> usize {
        self.pool.current_num_threads()
    }

    /// The renderer's threads, for other drivers of [`render_tile`]
    /// (adaptive rounds).
    pub(crate) fn pool(&self) -> &rayon::ThreadPool {
        &self.pool
    }

    /// Renders `region` (its rect of its frame over its sample indices).
    /// `progress` is called from the worker threads with the number of
    /// pixel-samples each finished tile covered.
    pub fn render(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Result<Film, RenderError> {
        let never = AtomicBool::new(false);
        Ok(self
            .render_until(prepared, region, progress, &never)?
            .expect("never cancelled"))
    }

    /// As [`Self::render`], but stops once `cancel` is set: tiles not yet
    /// started are skipped and `None` comes back. One parallel pass over
    /// the whole rect (one barrier at its end), cancelled within a tile.
    pub fn render_until(
        &self,
        prepared: &PreparedFrame,
        region: WorkRegion,
        progress: &(dyn Fn(u64) + Sync),
        cancel: &AtomicBool,
    ) -> Result<Option<Film>, RenderError> {
        let WorkRegion {
            frame,
            rect,
            samples,
        } = region;
        prepared.check_request(rect, samples)?;
        Ok(match prepared {
            PreparedFrame::F32(w) => self.render_world(w, frame, rect, samples, progress, cancel),
            PreparedFrame::F64(w) => self.render_world(w, frame, rect, samples, progress, cancel),
        })
    }

    fn render_world<R: Real>(
        &self,
        world: &World<R>,
        frame: u32,
        rect: Rect,
        samples: SampleRange,
        progress: &(dyn Fn(u64) + Sync),
        cancel: &AtomicBool,
    ) -> Option<Film> {
        self.pool.install(|| world.make_texture_levels());
        let pieces = pieces(rect, samples, self.threads());
        let films: Vec<Option<Film>> = self.pool.install(|| {
            pieces
                .par_iter()
                // One piece a task: rayon would otherwise stop splitting at
                // a few pieces a thread, and a thread that finished its own
                // waited for the other's last piece (up to a quarter of the
                // rect with two threads: a farm unit took 7% longer than
                // its share of one call over the frame).
                .with_max_len(1)
                .map(|&(tile, samples)| {
                    if cancel.load(Ordering::Relaxed) {
                        return None;
                    }
                    let film = render_tile(world, frame, tile, samples);
                    progress(tile.area() as u64 * samples.len() as u64);
                    Some(film)
                })
                .collect()
        });
        if cancel.load(Ordering::Relaxed) {
            return None;
        }
        let films: Vec<Film> = films.into_iter().collect::<Option<_>>()?;
        let mut out = Film::new(rect);
        for f in &films {
            out.merge(f)
                .expect("tiles lie inside their rect and sums cannot overflow");
        }
        Some(out)
    }
}

/// The tasks of a render of `rect` over `samples` on `threads`: its
/// tiles, each over all the samples where there are at least
/// [`TASKS_PER_THREAD`] tiles a thread, else over as many slices of the
/// samples as bring the count there. A small frame on many threads (320x240
/// is 300 tiles, 19 for each of 16) otherwise ends with threads idle behind
/// a few costly tiles. Sums are integers and each sample index draws the
/// same numbers whatever the slice, so the film is the same bit for bit.
fn pieces(rect: Rect, samples: SampleRange, threads: usize) -> Vec<(Rect, SampleRange)> {
    let tiles = rect.tiles(TILE);
    let want = TASKS_PER_THREAD * threads.max(1);
    let slices = want
        .div_ceil(tiles.len().max(1))
        .clamp(1, samples.len().max(1) as usize) as u32;
    let step = samples.len().div_ceil(slices);
    tiles
        .into_iter()
        .flat_map(|tile| samples.batches(step).map(move |s| (tile, s)))
        .collect()
}

/// Tasks a thread should have for the last ones to leave little idle: the
/// adaptive rounds' pieces take the same figure.
pub(crate) const TASKS_PER_THREAD: usize = 32;

/// Renders one tile on the calling thread: the stream renderer where it
/// applies (at the best SIMD level of this CPU), else [`render_tile_recursive`].
pub fn render_tile<R: Real>(
    world: &World<R>,
    frame: u32,
    tile: Rect,
    samples: SampleRange,
) -> Film {
    if let Some(dist) = &world.dist {
        return distributed::render_tile(world, dist, frame, tile, samples);
    }
    if let Some(w) = (world as &dyn std::any::Any).downcast_ref::<World<f32>>()
        && stream::supports(w)
    {
        return stream::render_tile(w, frame, tile, samples, crate::simd::level());
    }
    render_tile_recursive(world, frame, tile, samples)
}

/// Renders one tile on the calling thread with the recursive reference
/// shading (`step::shade` with [`Static`] effects, step by step). Camera rays go in packets: for
/// each 4x4-pixel block of the tile and each sample index, the block's rays
/// are traced together ([`World::closest_hits`]: in a tree, neighbouring
/// camera rays visit the same nodes), then each light's shadow rays from
/// their hits ([`World::occluded_many`]); both give the answers of one ray
/// at a time, each colour adds its terms in `shade`'s order, and the film's
/// fixed-point sums do not depend on the order samples arrive in, so the
/// film is that of `shade` ray by ray.
pub fn render_tile_recursive<R: Real>(
    world: &World<R>,
    frame: u32,
    tile: Rect,
    samples: SampleRange,
) -> Film {
    const BLOCK: u32 = 4;
    let mut film = Film::new(tile);
    let mut rays = RayCounts::default();
    let s = &world.settings;
    let mut packet: Vec<Ray<R>> = Vec::with_capacity((BLOCK * BLOCK) as usize);
    let mut hits = [None; (BLOCK * BLOCK) as usize];
    let mut surfaces: Vec<Option<Surface<R, PrimId>>> =
        Vec::with_capacity((BLOCK * BLOCK) as usize);
    let mut colours: Vec<R::V3> = Vec::with_capacity((BLOCK * BLOCK) as usize);
    // Each light's shadow rays of a block: pixel in the block and what it adds unblocked.
    let mut shadows: Vec<(usize, R::V3)> = Vec::with_capacity((BLOCK * BLOCK) as usize);
    let mut shadow_rays: Vec<Ray<R>> = Vec::with_capacity((BLOCK * BLOCK) as usize);
    let mut shadow_t: Vec<R> = Vec::with_capacity((BLOCK * BLOCK) as usize);
    let mut shadow_skip: Vec<PrimId> = Vec::with_capacity((BLOCK * BLOCK) as usize);
    let mut blocked = [false; (BLOCK * BLOCK) as usize];
    let mut pixels = [(0usize, 0u32, 0u32, 0u32); (BLOCK * BLOCK) as usize];
    for by in (tile.y..tile.y + tile.height).step_by(BLOCK as usize) {
        for bx in (tile.x..tile.x + tile.width).step_by(BLOCK as usize) {
            // The block's pixels: film index, position and seed.
            let mut n = 0;
            for y in by..(by + BLOCK).min(tile.y + tile.height) {
                for x in bx..(bx + BLOCK).min(tile.x + tile.width) {
                    let i = ((y - tile.y) * tile.width + (x - tile.x)) as usize;
                    pixels[n] = (i, x, y, pixel_seed(x, y, frame));
                    n += 1;
                }
            }
            for sample in samples.start..samples.end {
                packet.clear();
                for &(_, x, y, seed) in &pixels[..n] {
                    let (u, v) = sample_offset(s.sampler, s.samples, seed, sample);
                    let sx = R::from_u32(x) + R::from_f64(u as f64);
                    let sy = R::from_u32(y) + R::from_f64(v as f64);
                    packet.push(world.camera.ray(sx, sy));
                }
                world.closest_hits(&packet, PrimId::NONE, &mut hits[..n]);
                // `shade`'s steps, with each light's shadow rays of the block
                // traced together; every colour sums its terms in `shade`'s order.
                surfaces.clear();
                colours.clear();
                for (ray, hit) in packet.iter().zip(hits) {
                    rays.primary += 1;
                    let s = hit.map(|h| Surface::at(world, ray, h));
                    colours.push(s.as_ref().map_or(world.background, |s| s.ambient(world)));
                    surfaces.push(s);
                }
                for light in &world.lights {
                    shadows.clear();
                    shadow_rays.clear();
                    shadow_t.clear();
                    shadow_skip.clear();
                    for (k, s) in surfaces.iter().enumerate() {
                        let Some(s) = s else { continue };
                        if let Some(l) = s.light_term(light.position, light) {
                            rays.shadow += 1;
                            shadow_rays.push(l.shadow);
                            shadow_t.push(l.t_max);
                            shadow_skip.push(s.prim);
                            shadows.push((k, l.contrib));
                        }
                    }
                    let m = shadows.len();
                    world.occluded_many(&shadow_rays, &shadow_t, &shadow_skip, &mut blocked[..m]);
                    for (&(k, contrib), &b) in shadows.iter().zip(&blocked[..m]) {
                        if !b {
                            colours[k] += contrib;
                        }
                    }
                }
                for ((s, c), &(i, ..)) in surfaces.iter().zip(colours.iter_mut()).zip(&pixels[..n])
                {
                    if let Some(s) = s {
                        s.add_secondary(world, &Static, 0, (), &mut rays, c);
                    }
                    film.add_sample::<R>(i, [c.x(), c.y(), c.z()]);
                }
            }
        }
    }
    film.rays = rays;
    film
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every pixel-sample once, in as many tasks as `TASKS_PER_THREAD`
    /// asks where the samples allow.
    #[test]
    fn pieces_cover_each_pixel_sample_once() {
        let rect = Rect::new(3, 5, 70, 40);
        for (samples, threads) in [(1, 1), (9, 1), (9, 16), (1024, 16), (1024, 10_000)] {
            let range = SampleRange::new(7, 7 + samples);
            let pieces = pieces(rect, range, threads);
            let mut hits = vec![0u32; rect.area() * samples as usize];
            for (tile, s) in &pieces {
                assert!(rect.contains(tile) && !s.is_empty() && s.start >= 7 && s.end <= range.end);
                for y in tile.y..tile.y + tile.height {
                    for x in tile.x..tile.x + tile.width {
                        for k in s.start..s.end {
                            let p =
                                (y - rect.y) as usize * rect.width as usize + (x - rect.x) as usize;
                            hits[p * samples as usize + (k - 7) as usize] += 1;
                        }
                    }
                }
            }
            assert!(
                hits.iter().all(|&h| h == 1),
                "{samples} spp, {threads} threads"
            );
            let tiles = rect.tiles(TILE).len();
            let want = (TASKS_PER_THREAD * threads).min(tiles * samples as usize);
            assert!(
                pieces.len() >= want,
                "{samples} spp, {threads} threads: {} pieces",
                pieces.len()
            );
        }
    }
}
