//! import sums.wgsl
//! uses radiance: whitted.wgsl or path.wgsl
// The stack driver's entry, one for both integrators: one invocation per
// pixel-sample of the dispatch's rows (sums.wgsl's grid), whose camera
// ray's colour is `radiance`, defined by the kernel's integrator
// (whitted.wgsl's ray tree or path.wgsl's path; the host names one as a
// root), added to its pixel's sums.
@compute @workgroup_size(WG_X, WG_Y, 1)
fn render(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let col = gid.x;
    let row = params.row0 + gid.y;
    var s = params.sample_start + gid.z;
    var p = vec4<u32>(0u);
    if (col < params.rect_w && gid.y < params.rows && row < params.rect_h && s < params.sample_end) {
        p = grid_pixel(col, row);
        s = block_sample(row, s);
        if (s == NO_SAMPLE) {
            p = vec4<u32>(0u);
        }
    }
    if (p.w != 0u) {
        let seed = pixel_seed(p.x, p.y, params.frame);
        let ray = camera_ray(p.x, p.y, seed, s);
        tally[C_PRIMARY] += 1u;
        add_sample(p.z, radiance(ray.origin, ray.dir, seed, s, ray.tau));
    }
    flush_tally(lid);
}
