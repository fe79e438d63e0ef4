//! import shade.wgsl
//! import sums.wgsl
//! import wave_queue.wgsl
// The thesis's weighted ray tasks as a wavefront: instead of one thread
// walking a sample's whole ray tree, each generation of rays is a queue of
// tasks (pixel, weight, ray, depth, skip); one dispatch shades a whole
// generation, adds weight * local colour to the task's pixel (atomically, in
// 32.32 fixed point) and appends the children to the next queue. The
// step is shade.wgsl's, as the stack driver's. For scenes without
// distributed effects (rays carry no node key or time).

// Keep in sync with layout.rs WaveTask (48 bytes).
struct WaveTask {
    origin: vec3<f32>,
    weight: f32,
    dir: vec3<f32>,
    depth: u32,
    skip: u32,
    // Index of the task's pixel in the film (row-major over the rect).
    pixel: u32,
}

// Primary tasks of the dispatch's band of rows x range of samples, written
// to queue_out (the host then binds it as the next pass's queue_in).
@compute @workgroup_size(WG_X * WG_Y, 1, 1)
fn wave_primary(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let n = primary_tasks();
    let i = gid.x;
    if (i < n) {
        let t = primary_task(i);
        let ray = camera_ray(t.px, t.py, t.seed, t.sample);
        queue_out[i] = WaveTask(vec3<f32>(0.0), 1.0, ray.dir, 0u, NONE, t.index);
        tally[C_PRIMARY] += 1u;
    }
    if (i == 0u) {
        atomicStore(&wave.count_out, n);
    }
    flush_tally(lid);
}

// One generation: every task of queue_in, shaded as render/step.rs does.
@compute @workgroup_size(WG_X * WG_Y, 1, 1)
fn wave_shade(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = gid.x;
    if (i < atomicLoad(&wave.count_in)) {
        let task = queue_in[i];
        let r = shade(Ray(task.origin, task.weight, task.dir, task.depth, task.skip, ROOT_KEY), 0u, 0u, 0.0);
        let colour = r.colour * task.weight;
        if (r.has_refracted) {
            let c = r.refracted;
            push(WaveTask(c.origin, c.weight, c.dir, c.depth, c.skip, task.pixel));
        }
        if (r.has_reflected) {
            let c = r.reflected;
            push(WaveTask(c.origin, c.weight, c.dir, c.depth, c.skip, task.pixel));
        }
        let base = task.pixel * 6u;
        add_fixed(base, colour.x);
        add_fixed(base + 2u, colour.y);
        add_fixed(base + 4u, colour.z);
    }
    flush_tally(lid);
}
