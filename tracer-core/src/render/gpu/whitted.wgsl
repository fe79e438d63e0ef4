//! import shade.wgsl
//! import sums.wgsl
// The thesis's Whitted model on the GPU, the stack driver: one invocation
// per pixel-sample; the sample's ray tree is walked with a bounded
// per-thread task stack (WGSL has no recursion), each ray shaded by
// shade.wgsl's step, and its radiance added to its pixel's sums
// (sums.wgsl). A pixel's colour is the sum over the tree of weight * local
// colour, the same quantity the CPU's recursion in `render/step.rs`
// (with distributed effects, `render/cpu/distributed.rs`) computes.

// Colour of one camera ray: render/step.rs `trace`, unrolled.
fn trace(origin: vec3<f32>, dir: vec3<f32>, seed: u32, s: u32, tau: f32) -> vec3<f32> {
    var stack: array<Ray, STACK_CAP>;
    var top = 0u;
    var task = Ray(origin, 1.0, dir, 0u, NONE, ROOT_KEY);
    var colour = vec3<f32>(0.0);
    loop {
        let r = shade(task, seed, s, tau);
        colour += r.colour * task.weight;
        var have_next = r.has_refracted;
        var next = r.refracted;
        if (r.has_reflected) {
            // Both children: keep one pending (at most one per generation).
            if (have_next && top < STACK_CAP) {
                stack[top] = next;
                top += 1u;
            }
            next = r.reflected;
            have_next = true;
        }
        if (have_next) {
            task = next;
        } else if (top > 0u) {
            top -= 1u;
            task = stack[top];
        } else {
            break;
        }
    }
    return colour;
}

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
        add_sample(p.z, trace(ray.origin, ray.dir, seed, s, ray.tau));
    }
    flush_tally(lid);
}
