//! What each tile of a job costs, estimated before any worker renders it.
//!
//! Pixels of one frame differ in cost by two orders of magnitude (open sky
//! against a stack of glass spheres), so a worker's speed in pixel-samples
//! per second, measured on one part of a frame, sizes leases badly on
//! another: a lease sized on sky tiles took 2.3 s instead of 0.25 s on
//! glass, and at a job's end the other workers waited for it. Rays cost
//! about the same wherever they are traced, so leases are sized in rays:
//! a worker's speed in rays per second (from its results' ray counts)
//! against each tile's expected rays, estimated here by tracing a few
//! sparse one-sample pixels of each tile on the coordinator.

use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::cpu::render_tile;
use tracer_core::render::{Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};

use crate::units::Layout;

/// Probe pixels traced for one job at most (a k x k grid per tile, k <= 4).
const MAX_PROBES: usize = 1 << 15;

/// Expected rays of one pixel-sample pass over each tile of `layout` (one
/// entry per tile): the mean rays of the tile's probe pixels times its
/// area. Frames are taken to cost what the first one does.
pub fn probe(scene: &SceneDesc, settings: &RenderSettings, layout: &Layout) -> Vec<f64> {
    let uniform = || layout.tiles.iter().map(|t| t.area() as f64).collect();
    let Ok(PreparedFrame::F32(world)) =
        PreparedFrame::build(scene, settings, layout.first_frame, Precision::F32)
    else {
        return uniform();
    };
    let k = ((MAX_PROBES / layout.tiles.len().max(1)) as f64)
        .sqrt()
        .floor()
        .clamp(1.0, 4.0) as u32;
    layout
        .tiles
        .iter()
        .map(|t| {
            let (kx, ky) = (k.min(t.width), k.min(t.height));
            let mut rays = 0;
            for j in 0..ky {
                for i in 0..kx {
                    // The centre of each cell of a kx x ky grid over the tile.
                    let x = t.x + (2 * i + 1) * t.width / (2 * kx);
                    let y = t.y + (2 * j + 1) * t.height / (2 * ky);
                    let film = render_tile(
                        &world,
                        layout.first_frame,
                        Rect::new(x, y, 1, 1),
                        SampleRange::new(0, 1),
                    );
                    rays += film.rays.total();
                }
            }
            // At least one ray a pixel-sample (the primary), so that no tile is free.
            (rays as f64 / (kx * ky) as f64).max(1.0) * t.area() as f64
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glass_costs_more_than_sky_and_every_tile_costs_at_least_its_primary_rays() {
        // A glass sphere at world -x: the right half of the image (the
        // camera's right is f x up = -x), nothing on the left.
        let scene = SceneDesc::parse(
            r#"
[render]
width = 128
height = 64
max_depth = 8
[camera]
position = [0, 0, -5]
look_at = [0, 0, 0]
fov_y = 40
[materials.glass]
diffuse = [0.1, 0.1, 0.1]
reflectivity = 0.1
transparency = 0.9
ior = 1.5
[[lights]]
position = [0, 5, -5]
diffuse = [1, 1, 1]
[[objects]]
type = "sphere"
center = [-1.2, 0, 0]
radius = 0.9
material = "glass"
"#,
            "probe.toml",
        )
        .unwrap();
        let layout = Layout::new(128, 64, 4, 0, 0, 32, 4);
        let cost = probe(&scene, &scene.render, &layout);
        assert_eq!(cost.len(), 8);
        // Rows of 4 tiles: the sphere covers tiles 2 and 6 (x 64..96); the left half is empty.
        assert!(cost[2] > 4.0 * cost[0], "{cost:?}");
        assert!(cost[6] > 4.0 * cost[4], "{cost:?}");
        // Empty tiles: one primary ray per pixel-sample, nothing else.
        assert_eq!(
            (cost[0], cost[1], cost[4], cost[5]),
            (1024.0, 1024.0, 1024.0, 1024.0),
            "{cost:?}"
        );
        assert!(cost.iter().all(|&c| c >= 1024.0));
    }
}
