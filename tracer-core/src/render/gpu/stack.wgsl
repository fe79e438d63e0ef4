//! import sums.wgsl
//! uses radiance: whitted.wgsl or path.wgsl
// The stack driver's entry, one for both integrators: one invocation per
// pixel-sample of the dispatch's rows (sums.wgsl's grid), or in a listed
// dispatch per pixel and chunk of samples (sums.wgsl listed_work), whose camera
// ray's colour is `radiance`, defined by the kernel's integrator
// (whitted.wgsl's ray tree or path.wgsl's path; the host names one as a
// root), added to its pixel's sums.
@compute @workgroup_size(WG_X, WG_Y, 1)
fn render(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    if (ADAPTIVE && params.ranged != 0u) {
        // A listed dispatch: each invocation one pixel over a few samples,
        // summed in registers first (sums.wgsl listed_work).
        let w = listed_work((wid.y * groups.x + wid.x) * (WG_X * WG_Y) + lid);
        if (w.pixel.w != 0u) {
            let seed = pixel_seed(w.pixel.x, w.pixel.y, params.frame);
            var acc = PixelSums();
            for (var s = w.first; s < w.end; s++) {
                let ray = camera_ray(w.pixel.x, w.pixel.y, seed, s);
                tally[C_PRIMARY] += 1u;
                acc = accumulate(acc, radiance(ray.origin, ray.dir, seed, s, ray.tau));
            }
            add_sums(w.pixel.z, acc);
            // The rays it traced, booked to its block: the error-optimal
            // mode's cost of a block (optimal.rs Costs), as the CPU books
            // its runs'. The tally held nothing before the loop.
            let rays = tally[C_PRIMARY] + tally[C_SHADOW] + tally[C_REFLECTION] + tally[C_REFRACTION];
            if (rays != 0u) {
                let old = atomicAdd(&block_rays[2u * w.block], rays);
                if (old + rays < old) {
                    atomicAdd(&block_rays[2u * w.block + 1u], 1u);
                }
            }
        }
        flush_tally(lid);
        return;
    }
    let col = gid.x;
    let row = params.row0 + gid.y;
    let s = params.sample_start + gid.z;
    var p = vec4<u32>(0u);
    if (col < params.rect_w && gid.y < params.rows && row < params.rect_h && s < params.sample_end) {
        p = grid_pixel(col, row);
    }
    if (p.w != 0u) {
        let seed = pixel_seed(p.x, p.y, params.frame);
        let ray = camera_ray(p.x, p.y, seed, s);
        tally[C_PRIMARY] += 1u;
        add_sample(p.z, radiance(ray.origin, ray.dir, seed, s, ray.tau));
    }
    flush_tally(lid);
}
