//! The stream (wavefront) renderer: f32 scenes of spheres and planes only
//! (no BVH, no triangles), which is every scene of the thesis's experiments.
//!
//! Instead of following one ray at a time down its tree of secondary rays,
//! a batch of primary rays is traced generation by generation: closest hits
//! for the whole generation ([`kernels::closest_hits`], `W` rays per lane
//! group against each primitive), then all hits are shaded `W` at a time
//! ([`shade_lanes`], the arithmetic of the recursive `step::trace`),
//! their shadow rays tested light by light ([`kernels::occluded`]), and a
//! scalar pass queues, hit by hit, the refracted and reflected rays: the
//! next generation, each with its parent and weight. When no generation is
//! left, colours are folded back up the tree, children into parents in
//! spawn order.
//!
//! Same bits as the recursive reference: every intersection and every
//! local shading does the same IEEE operations in the same order (no FMA
//! contraction: Rust never fuses a multiply and an add), and the fold adds
//! a hit's lights and children in `trace`'s order. A ray's value depends
//! only on the ray, so tiles, sample ranges, batches, thread counts and
//! SIMD levels cannot change a sample (tests/cpu_stream.rs checks all of
//! this).

use super::kernels::{self, Prims, RaySoa};
use super::shade::{Shaded, Tables, shade_lanes};
use crate::film::{Film, RayCounts, Rect, SampleRange};
use crate::geometry::PrimId;
use crate::sampling::{pixel_seed, same_in_every_pixel, sample_offset};
use crate::world::{Camera, World};

/// Primary rays traced together: enough to fill the lane groups many times
/// over, few enough that a generation's queues stay in L1/L2 (of 256, 1024
/// and 4096, 256 was fastest on the resolution scene).
const BATCH: usize = 256;

pub use crate::simd::SimdLevel;

/// Whether the stream renderer handles this world.
pub fn supports(world: &World<f32>) -> bool {
    world.accel.is_none() && world.triangle_count() == 0 && world.instances.list.is_empty()
}

/// Renders one tile with the stream renderer at SIMD level `level`, which
/// must be available on this CPU ([`SimdLevel::is_available`]; others fall
/// back to the baseline).
pub fn render_tile(
    world: &World<f32>,
    frame: u32,
    tile: Rect,
    samples: SampleRange,
    level: SimdLevel,
) -> Film {
    debug_assert!(supports(world));
    #[cfg(target_arch = "x86_64")]
    {
        if level == SimdLevel::Avx512 && level.is_available() {
            // SAFETY: the CPU supports AVX-512F (checked just above).
            return unsafe { render_tile_avx512(world, frame, tile, samples) };
        }
        if level == SimdLevel::Avx2 && level.is_available() {
            // SAFETY: the CPU supports AVX2 (checked just above).
            return unsafe { render_tile_avx2(world, frame, tile, samples) };
        }
    }
    let _ = level;
    render_tile_lanes::<8>(world, frame, tile, samples, false)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn render_tile_avx2(world: &World<f32>, frame: u32, tile: Rect, samples: SampleRange) -> Film {
    render_tile_lanes::<8>(world, frame, tile, samples, true)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn render_tile_avx512(world: &World<f32>, frame: u32, tile: Rect, samples: SampleRange) -> Film {
    render_tile_lanes::<16>(world, frame, tile, samples, true)
}

/// One generation of path rays of a batch, in structure-of-arrays form
/// from the start: spawning writes each ray straight into its lane arrays.
#[derive(Default)]
struct Generation {
    /// Rays spawned (the arrays are longer: padding and spare room).
    n: usize,
    rays: RaySoa,
    /// Index of the ray that spawned each (in the previous generation; for
    /// primary rays, the sample in the batch) ...
    parent: Vec<u32>,
    /// ... and the weight its colour adds to its parent's with.
    weight: Vec<f32>,
    /// Closest hits.
    t: Vec<f32>,
    id: Vec<u32>,
    /// Colour of each ray (x, y, z arrays): local shading (ambient, then
    /// unblocked lights), then its children's colours folded in.
    colour: [Vec<f32>; 3],
}

impl Generation {
    /// Makes room for `n` rays (plus padding to a lane group of `w`).
    fn reserve(&mut self, n: usize, w: usize) {
        let np = n.div_ceil(w) * w + w;
        self.rays.grow(np);
        grow(&mut self.parent, np);
        grow(&mut self.weight, np);
    }

    /// Writes ray `at` (room for it made by [`Self::reserve`]).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn set(&mut self, at: usize, o: [f32; 3], d: [f32; 3], skip: u32, parent: u32, weight: f32) {
        let r = &mut self.rays;
        r.ox[at] = o[0];
        r.oy[at] = o[1];
        r.oz[at] = o[2];
        r.dx[at] = d[0];
        r.dy[at] = d[1];
        r.dz[at] = d[2];
        r.skip[at] = skip;
        self.parent[at] = parent;
        self.weight[at] = weight;
    }

    /// Pads the `n` rays with harmless ones (results ignored) to a multiple
    /// of `w`; returns the padded count.
    fn pad(&mut self, w: usize) -> usize {
        let n = self.n;
        let np = n.div_ceil(w) * w;
        self.reserve(np, w);
        for i in n..np {
            self.set(i, [0.0; 3], [0.0, 0.0, 1.0], PrimId::NONE.0, 0, 0.0);
        }
        np
    }
}

/// `Camera::ray` through each raster point (`sx`, `sy`), lane by lane: the
/// same operations as glam's `Vec3A` arithmetic, component by component
/// (its dot product adds (x + y) + z; `normalize` is d * (1 / |d|)).
#[inline(always)]
fn primary_rays(cam: &Camera<f32>, sx: &[f32], sy: &[f32], g: &mut Generation) {
    let n = sx.len();
    let (f, r, u) = (
        <[f32; 3]>::from(cam.forward),
        <[f32; 3]>::from(cam.right),
        <[f32; 3]>::from(cam.up),
    );
    let rays = &mut g.rays;
    let (ox, oy, oz) = (&mut rays.ox[..n], &mut rays.oy[..n], &mut rays.oz[..n]);
    let (dx, dy, dz) = (&mut rays.dx[..n], &mut rays.dy[..n], &mut rays.dz[..n]);
    let (skip, parent, weight) = (&mut rays.skip[..n], &mut g.parent[..n], &mut g.weight[..n]);
    let sy = &sy[..n];
    for i in 0..n {
        let a = 2.0 * sx[i] * cam.inv_width - 1.0;
        let b = 1.0 - 2.0 * sy[i] * cam.inv_height;
        let d = [0, 1, 2].map(|c| f[c] + r[c] * a + u[c] * b);
        let inv = 1.0 / (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        (ox[i], oy[i], oz[i]) = (0.0, 0.0, 0.0);
        (dx[i], dy[i], dz[i]) = (d[0] * inv, d[1] * inv, d[2] * inv);
        (skip[i], parent[i], weight[i]) = (PrimId::NONE.0, i as u32, 1.0);
    }
    g.n = n;
}

#[inline(always)]
fn render_tile_lanes<const W: usize>(
    world: &World<f32>,
    frame: u32,
    tile: Rect,
    samples: SampleRange,
    select: bool,
) -> Film {
    let mut film = Film::new(tile);
    let mut rays = RayCounts::default();
    let prims = Prims::new(world);
    let tab = Tables::new(world, select);
    // Taken out and put back rather than borrowed in a closure: a closure
    // would not inherit the caller's `target_feature`s.
    let mut scratch = SCRATCH.take();
    trace_tile::<W>(
        world,
        frame,
        tile,
        samples,
        &prims,
        &tab,
        &mut scratch,
        &mut film,
        &mut rays,
    );
    SCRATCH.set(scratch);
    film.rays = rays;
    film
}

/// Buffers reused from tile to tile on each thread (growing them anew for
/// every tile costs more than the tracing of small tiles).
#[derive(Default)]
struct Scratch {
    gens: Vec<Generation>,
    sh: Shaded,
    /// Whether each shadow ray of a light is blocked.
    blocked: Vec<bool>,
    /// Film pixel of each sample of the batch, and its raster position.
    batch: Vec<usize>,
    raster_x: Vec<f32>,
    raster_y: Vec<f32>,
    /// Offset of each sample index, where the same in every pixel.
    offsets: Vec<(f32, f32)>,
}

/// Makes `v` at least `n` long; scratch is overwritten before it is read,
/// so it is never shrunk (and refilled) between generations.
fn grow<T: Copy + Default>(v: &mut Vec<T>, n: usize) {
    if v.len() < n {
        v.resize(n, T::default());
    }
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::default();
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn trace_tile<const W: usize>(
    world: &World<f32>,
    frame: u32,
    tile: Rect,
    samples: SampleRange,
    prims: &Prims,
    tab: &Tables,
    scratch: &mut Scratch,
    film: &mut Film,
    rays: &mut RayCounts,
) {
    let Scratch {
        gens,
        sh,
        blocked,
        batch,
        raster_x,
        raster_y,
        offsets,
    } = scratch;
    let s = &world.settings;
    let nl = world.lights.len();
    if gens.is_empty() {
        gens.push(Generation::default());
    }

    // Samples in `render_tile`'s order: pixels row by row, each pixel's
    // samples in turn. Offsets that do not depend on the pixel (the grid)
    // are computed once per tile, the same calls as per sample.
    let shared = same_in_every_pixel(s.sampler, s.samples);
    offsets.clear();
    if shared {
        offsets.extend(
            (samples.start..samples.end).map(|k| sample_offset(s.sampler, s.samples, 0, k)),
        );
    }
    let (x_end, y_end) = (tile.x + tile.width, tile.y + tile.height);
    let (mut pixel, mut x, mut y, mut k) = (0, tile.x, tile.y, samples.start);
    let mut seed = if shared { 0 } else { pixel_seed(x, y, frame) };
    grow(raster_x, BATCH);
    grow(raster_y, BATCH);
    grow(batch, BATCH);
    while y < y_end {
        let mut n = 0;
        while n < BATCH && y < y_end {
            let (u, v) = if shared {
                offsets[(k - samples.start) as usize]
            } else {
                sample_offset(s.sampler, s.samples, seed, k)
            };
            // As `render_tile`: R::from_u32(x) + R::from_f64(u as f64).
            raster_x[n] = x as f32 + u;
            raster_y[n] = y as f32 + v;
            batch[n] = pixel;
            n += 1;
            k += 1;
            if k == samples.end {
                (k, pixel, x) = (samples.start, pixel + 1, x + 1);
                if x == x_end {
                    (x, y) = (tile.x, y + 1);
                }
                if !shared && y < y_end {
                    seed = pixel_seed(x, y, frame);
                }
            }
        }
        gens[0].reserve(n, W);
        primary_rays(&world.camera, &raster_x[..n], &raster_y[..n], &mut gens[0]);
        rays.primary += n as u64;

        // Down the tree, generation by generation.
        let mut last = 0;
        for depth in 0..=s.max_depth as usize {
            if gens[depth].n == 0 {
                break;
            }
            last = depth;
            if gens.len() < depth + 2 {
                gens.push(Generation::default());
            }
            let (done, rest) = gens.split_at_mut(depth + 1);
            let (cur, next) = (&mut done[depth], &mut rest[0]);
            let n = cur.n;
            let np = cur.pad(W);
            kernels::closest_hits::<W>(prims, &cur.rays, np, &mut cur.t, &mut cur.id);
            let o = [&cur.rays.ox[..np], &cur.rays.oy[..np], &cur.rays.oz[..np]];
            let d = [&cur.rays.dx[..np], &cur.rays.dy[..np], &cur.rays.dz[..np]];
            shade_lanes::<W>(
                world,
                tab,
                o,
                d,
                &cur.t[..np],
                &cur.id[..np],
                depth as u32,
                sh,
            );
            // The local colours become this generation's (the buffers swap:
            // shading overwrites them next time).
            for (cc, sc) in cur.colour.iter_mut().zip(&mut sh.local) {
                std::mem::swap(cc, sc);
            }
            // Shadow rays, light by light over all hits (in place: a ray not
            // wanted is a lane reported blocked). Each hit's lights are
            // added in light order, as `trace` adds them.
            grow(blocked, np);
            for li in 0..nl {
                let r = li * np..(li + 1) * np;
                let o = [
                    &sh.light_origin[0][r.clone()],
                    &sh.light_origin[1][r.clone()],
                    &sh.light_origin[2][r.clone()],
                ];
                let d = [
                    &sh.light_dir[0][r.clone()],
                    &sh.light_dir[1][r.clone()],
                    &sh.light_dir[2][r.clone()],
                ];
                let on = &sh.light_on[r.clone()];
                kernels::occluded::<W>(
                    prims,
                    o,
                    d,
                    &cur.id,
                    &sh.light_t_max[r.clone()],
                    on,
                    blocked,
                );
                rays.shadow += on[..n].iter().map(|&b| b as u64).sum::<u64>();
                let base = li * np;
                let add = [
                    &sh.light_contrib[0][base..base + n],
                    &sh.light_contrib[1][base..base + n],
                    &sh.light_contrib[2][base..base + n],
                ];
                let [cx, cy, cz] = &mut cur.colour;
                let (cx, cy, cz) = (&mut cx[..n], &mut cy[..n], &mut cz[..n]);
                let (on, bl) = (&on[..n], &blocked[..n]);
                for i in 0..n {
                    if on[i] & !bl[i] {
                        cx[i] += add[0][i];
                        cy[i] += add[1][i];
                        cz[i] += add[2][i];
                    }
                }
            }
            // The next generation, hit by hit: the refracted ray, then the
            // reflected one, as `trace` spawns them.
            next.reserve(2 * n, W);
            let mut k = 0;
            {
                // Sliced to their lengths up front, so that the loop's
                // indexing is checked once, not per ray and array.
                let r = &mut next.rays;
                let cap = 2 * n;
                let (nox, noy, noz) = (&mut r.ox[..cap], &mut r.oy[..cap], &mut r.oz[..cap]);
                let (ndx, ndy, ndz) = (&mut r.dx[..cap], &mut r.dy[..cap], &mut r.dz[..cap]);
                let (nskip, nparent, nweight) = (
                    &mut r.skip[..cap],
                    &mut next.parent[..cap],
                    &mut next.weight[..cap],
                );
                let (ids, refract_on, transparency, reflect_w) = (
                    &cur.id[..n],
                    &sh.refract_on[..n],
                    &sh.transparency[..n],
                    &sh.reflect_w[..n],
                );
                let (below, rd) = (
                    sh.below.each_ref().map(|v| &v[..n]),
                    sh.refract_dir.each_ref().map(|v| &v[..n]),
                );
                let (above, fd) = (
                    sh.above.each_ref().map(|v| &v[..n]),
                    sh.reflect_dir.each_ref().map(|v| &v[..n]),
                );
                for i in 0..n {
                    if refract_on[i] {
                        (nox[k], noy[k], noz[k]) = (below[0][i], below[1][i], below[2][i]);
                        (ndx[k], ndy[k], ndz[k]) = (rd[0][i], rd[1][i], rd[2][i]);
                        (nskip[k], nparent[k], nweight[k]) = (ids[i], i as u32, transparency[i]);
                        k += 1;
                    }
                    if reflect_w[i] > 0.0 {
                        (nox[k], noy[k], noz[k]) = (above[0][i], above[1][i], above[2][i]);
                        (ndx[k], ndy[k], ndz[k]) = (fd[0][i], fd[1][i], fd[2][i]);
                        (nskip[k], nparent[k], nweight[k]) = (ids[i], i as u32, reflect_w[i]);
                        k += 1;
                    }
                }
            }
            let refractions = sh.refract_on[..n].iter().map(|&b| b as u64).sum::<u64>();
            rays.refraction += refractions;
            rays.reflection += k as u64 - refractions;
            next.n = k;
        }
        // Back up the tree: each ray's colour, weighted, into its parent's,
        // children in spawn order (refracted, then reflected), which is
        // `trace`'s `colour += trace(..) * weight`, operation for operation.
        for g in (1..=last).rev() {
            let (upper, lower) = gens.split_at_mut(g);
            let (parents, children) = (&mut upper[g - 1], &lower[0]);
            let m = children.n;
            let (w, p) = (&children.weight[..m], &children.parent[..m]);
            let [px, py, pz] = &mut parents.colour;
            let (px, py, pz) = (
                &mut px[..parents.n],
                &mut py[..parents.n],
                &mut pz[..parents.n],
            );
            let [cx, cy, cz] = &children.colour;
            let (cx, cy, cz) = (&cx[..m], &cy[..m], &cz[..m]);
            // One pass over the children for all three components, over
            // slices cut to length first (checked indexing per element
            // cost more than the arithmetic).
            for i in 0..m {
                let (p, w) = (p[i] as usize, w[i]);
                px[p] += cx[i] * w;
                py[p] += cy[i] * w;
                pz[p] += cz[i] * w;
            }
        }
        let [cx, cy, cz] = &gens[0].colour;
        for (i, &pixel) in batch[..n].iter().enumerate() {
            film.add_sample::<f32>(pixel, [cx[i], cy[i], cz[i]]);
        }
    }
}
