//! import path.wgsl
//! import sums.wgsl
//! import wave_queue.wgsl
// The path integrator as a wavefront (`Strategy::Wavefront`): each
// generation is a queue of paths between two segments; one dispatch runs
// path.wgsl's `path_step` once for every path of a generation and appends
// those that go on to the next queue, and a path that ends adds its
// radiance to its pixel. The step is the stack driver's (`radiance`
// loops over it), in the same order: a pixel's sums are the stack kernel's.

// Keep in sync with layout.rs PATH_WAVE_TASK_BYTES (80 bytes).
struct WaveTask {
    path: PathState,
    // The first word of the path's pixel's sums.
    word: u32,
    seed: u32,
    sample: u32,
    tau: f32,
}

// Primary paths of the dispatch's band of rows x range of samples, written
// to queue_out (the host then binds it as the next pass's queue_in).
@compute @workgroup_size(WG_X * WG_Y, 1, 1)
fn path_wave_primary(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let n = primary_tasks();
    let i = gid.x;
    if (i < n) {
        let t = primary_task(i);
        let ray = camera_ray(t.px, t.py, t.seed, t.sample);
        tally[C_PRIMARY] += 1u;
        // No segment at depth 0: the path adds nothing (path.wgsl `radiance`).
        if (MAX_DEPTH != 0u) {
            queue_out[i] = WaveTask(path_start(ray.origin, ray.dir), t.index * 6u, t.seed, t.sample, ray.tau);
        }
    }
    if (i == 0u) {
        atomicStore(&wave.count_out, select(n, 0u, MAX_DEPTH == 0u));
    }
    flush_tally(lid);
}

// One generation: a segment of every path of queue_in.
@compute @workgroup_size(WG_X * WG_Y, 1, 1)
fn path_wave_shade(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = gid.x;
    if (i < atomicLoad(&wave.count_in)) {
        var task = queue_in[i];
        var st = task.path;
        if (path_step(&st, task.seed, task.sample, task.tau)) {
            task.path = st;
            push(task);
        } else {
            add_sample(task.word, st.radiance);
        }
    }
    flush_tally(lid);
}
