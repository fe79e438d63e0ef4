//! import scene.wgsl
// The task queues of a wavefront driver (wavefront.wgsl for Whitted,
// path_wave.wgsl for paths): each generation's tasks in queue_in, its
// children appended to queue_out, swapped between generations. The task
// type, `WaveTask`, is the driver's.

// Keep in sync with layout.rs WaveState.
struct WaveState {
    // Tasks in the input queue, the output queue's append cursor.
    count_in: atomic<u32>,
    count_out: atomic<u32>,
    // Set when a generation had more children than the queue holds.
    overflow: atomic<u32>,
}

override QUEUE_CAP: u32 = 1u;

// Groups 1 (queue_in, queue_out, wave) and 2 (wave_args_out): wgsl.rs
// WAVE_QUEUES and WAVE_ARGS.

fn wave_args(n: u32) -> vec3<u32> {
    return vec3<u32>((n + WG_X * WG_Y - 1u) / (WG_X * WG_Y), 1u, 1u);
}

// Between generations (one invocation): the output queue becomes the next
// input; its length sets the next shade dispatch's size.
@compute @workgroup_size(1, 1, 1)
fn wave_swap() {
    let produced = atomicLoad(&wave.count_out);
    let n = min(produced, QUEUE_CAP);
    if (produced > QUEUE_CAP) {
        atomicStore(&wave.overflow, 1u);
    }
    atomicStore(&wave.count_in, n);
    atomicStore(&wave.count_out, 0u);
    let args = wave_args(n);
    wave_args_out[0] = args.x;
    wave_args_out[1] = args.y;
    wave_args_out[2] = args.z;
}

// Primary tasks of a dispatch: its band of rows x its range of samples.
fn primary_tasks() -> u32 {
    return params.rect_w * params.rows * (params.sample_end - params.sample_start);
}

// Primary task i (< primary_tasks()) of a dispatch: its pixel (in the
// image, and its index in the film, row-major over the rect), its
// sample and the pixel's seed.
struct Primary {
    px: u32,
    py: u32,
    index: u32,
    sample: u32,
    seed: u32,
}

fn primary_task(i: u32) -> Primary {
    let per_sample = params.rect_w * params.rows;
    let k = i % per_sample;
    let col = k % params.rect_w;
    let row = params.row0 + k / params.rect_w;
    let px = params.rect_x + col;
    let py = params.rect_y + row;
    return Primary(px, py, row * params.rect_w + col, params.sample_start + i / per_sample, pixel_seed(px, py, params.frame));
}

fn push(t: WaveTask) {
    let at = atomicAdd(&wave.count_out, 1u);
    if (at < QUEUE_CAP) {
        queue_out[at] = t;
    }
}

