//! import shade.wgsl
//! import sums.wgsl
//! import stack.wgsl
// The thesis's Whitted model on the GPU, the stack driver: one invocation
// per pixel-sample; the sample's ray tree is walked with a bounded
// per-thread task stack (WGSL has no recursion), each ray shaded by
// shade.wgsl's step, and its radiance added to its pixel's sums
// (sums.wgsl). A pixel's colour is the sum over the tree of weight * local
// colour, the same quantity the CPU's recursion in `render/step.rs`
// (with distributed effects, `render/cpu/distributed.rs`) computes.

// Colour of one camera ray (stack.wgsl's `radiance`): render/step.rs
// `trace`, unrolled.
fn radiance(origin: vec3<f32>, dir: vec3<f32>, seed: u32, s: u32, tau: f32) -> vec3<f32> {
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
