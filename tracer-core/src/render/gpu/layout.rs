//! Host mirrors of every structure the WGSL kernel reads or writes.
//!
//! Keep in sync with the struct declarations at the top of `whitted.wgsl`:
//! same field order, same sizes, WGSL alignment rules (a `vec3<f32>` is
//! 16-byte aligned, so each one is followed by a scalar that fills its
//! fourth lane). The `const` asserts below pin the sizes WGSL expects.

use bytemuck::{Pod, Zeroable};

use crate::geometry::{Plane, Sphere};
use crate::world::{Material, PointLight, World};

/// Per-scene constants. WGSL: `struct Frame`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
pub struct FrameUniform {
    pub forward: [f32; 3],
    pub inv_width: f32,
    pub right: [f32; 3],
    pub inv_height: f32,
    pub up: [f32; 3],
    /// Samples per pixel of the whole frame (the sampler's `count`).
    pub samples: u32,
    pub ambient: [f32; 3],
    /// n if `samples` = n*n, else 0 (R2 points).
    pub grid_n: u32,
    pub background: [f32; 3],
    /// 0 = grid, 1 = jittered.
    pub sampler: u32,
}

/// Per-dispatch parameters, read at a dynamic offset. WGSL: `struct Dispatch`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq, Eq)]
pub struct DispatchParams {
    /// The film's rectangle in image pixels.
    pub rect_x: u32,
    pub rect_y: u32,
    pub rect_w: u32,
    pub rect_h: u32,
    /// Band of rows (relative to the rect) this dispatch covers.
    pub row0: u32,
    pub rows: u32,
    /// Sample indices this dispatch adds.
    pub sample_start: u32,
    pub sample_end: u32,
    pub frame: u32,
    pub _pad: [u32; 3],
}

/// WGSL: `struct Sphere`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuSphere {
    pub center: [f32; 3],
    pub radius: f32,
    pub material: u32,
    pub _pad: [u32; 3],
}

/// WGSL: `struct Plane`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuPlane {
    pub normal: [f32; 3],
    pub distance: f32,
    pub material: u32,
    pub _pad: [u32; 3],
}

/// WGSL: `struct Material`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuMaterial {
    pub ambient: [f32; 3],
    pub shininess: f32,
    pub diffuse: [f32; 3],
    pub reflectivity: f32,
    pub specular: [f32; 3],
    pub transparency: f32,
    pub ior: f32,
    /// N.H below which the specular term is skipped (`Material::specular_cos_min`).
    pub specular_cos_min: f32,
    pub _pad: [f32; 2],
}

/// WGSL: `struct Light`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuLight {
    pub position: [f32; 3],
    pub _pad0: f32,
    pub diffuse: [f32; 3],
    pub _pad1: f32,
    pub specular: [f32; 3],
    pub _pad2: f32,
}

/// Per-pixel output: fixed-point sums as (low, high) u32 words per channel,
/// i.e. the `u64` sums of [`crate::film::Film`]. WGSL: `sums: array<u32>`, 6 words a pixel.
pub const SUM_WORDS: usize = 6;

/// Global counters, each a (low, high) u32 pair. WGSL: `counters: array<atomic<u32>, 10>`.
pub const COUNTERS: usize = 5;
pub const COUNTER_PRIMARY: usize = 0;
pub const COUNTER_SHADOW: usize = 1;
pub const COUNTER_REFLECTION: usize = 2;
pub const COUNTER_REFRACTION: usize = 3;
pub const COUNTER_NONFINITE: usize = 4;

/// A ray task of the wavefront strategy. WGSL (wavefront.wgsl): `struct WaveTask`.
pub const WAVE_TASK_BYTES: u64 = 48;
/// WGSL: `struct WaveState` (count_in, count_out, overflow), padded.
pub const WAVE_STATE_BYTES: u64 = 16;
/// WGSL: `wave_args_out: array<u32, 3>`, an indirect dispatch's x, y, z.
pub const WAVE_ARGS_BYTES: u64 = 12;

const _: () = assert!(size_of::<FrameUniform>() == 80);
const _: () = assert!(size_of::<DispatchParams>() == 48);
const _: () = assert!(size_of::<GpuSphere>() == 32);
const _: () = assert!(size_of::<GpuPlane>() == 32);
const _: () = assert!(size_of::<GpuMaterial>() == 64);
const _: () = assert!(size_of::<GpuLight>() == 48);

/// Everything the kernel needs of one frame of a scene, packed for upload.
/// Arrays are never empty (bindings must not be): an absent kind gets one
/// unused element, and its count (a pipeline constant) stays 0.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneData {
    pub frame: FrameUniform,
    pub spheres: Vec<GpuSphere>,
    pub planes: Vec<GpuPlane>,
    pub materials: Vec<GpuMaterial>,
    pub lights: Vec<GpuLight>,
    pub n_spheres: u32,
    pub n_planes: u32,
    pub n_lights: u32,
    pub max_depth: u32,
    pub has_reflection: bool,
    pub has_refraction: bool,
}

fn a3(v: glam::Vec3A) -> [f32; 3] {
    v.to_array()
}

fn non_empty<T: Default>(mut v: Vec<T>) -> Vec<T> {
    if v.is_empty() {
        v.push(T::default());
    }
    v
}

impl SceneData {
    pub fn from_world(w: &World<f32>) -> Self {
        let s = &w.settings;
        let grid_n = crate::sampling::exact_sqrt(s.samples).unwrap_or(0);
        let frame = FrameUniform {
            forward: a3(w.camera.forward),
            inv_width: w.camera.inv_width,
            right: a3(w.camera.right),
            inv_height: w.camera.inv_height,
            up: a3(w.camera.up),
            samples: s.samples,
            ambient: a3(w.ambient),
            grid_n,
            background: a3(w.background),
            sampler: match s.sampler {
                crate::sampling::Sampler::Grid => 0,
                crate::sampling::Sampler::Jittered => 1,
            },
        };
        let sphere = |s: &Sphere<f32>| GpuSphere { center: a3(s.center), radius: s.radius, material: s.material, _pad: [0; 3] };
        let plane = |p: &Plane<f32>| GpuPlane { normal: a3(p.normal), distance: p.distance, material: p.material, _pad: [0; 3] };
        let material = |m: &Material<f32>| GpuMaterial {
            ambient: a3(m.ambient),
            shininess: m.shininess,
            diffuse: a3(m.diffuse),
            reflectivity: m.reflectivity,
            specular: a3(m.specular),
            transparency: m.transparency,
            ior: m.ior,
            specular_cos_min: m.specular_cos_min,
            _pad: [0.0; 2],
        };
        let light = |l: &PointLight<f32>| GpuLight {
            position: a3(l.position),
            diffuse: a3(l.diffuse),
            specular: a3(l.specular),
            ..Default::default()
        };
        SceneData {
            frame,
            spheres: non_empty(w.spheres.iter().map(sphere).collect()),
            planes: non_empty(w.planes.iter().map(plane).collect()),
            materials: non_empty(w.materials.iter().map(material).collect()),
            lights: non_empty(w.lights.iter().map(light).collect()),
            n_spheres: w.spheres.len() as u32,
            n_planes: w.planes.len() as u32,
            n_lights: w.lights.len() as u32,
            max_depth: s.max_depth,
            has_reflection: w.features.reflection,
            has_refraction: w.features.refraction,
        }
    }

    /// Entries of the per-thread task stack the kernel needs: the kernel
    /// continues with one child and pushes the other, so only a node with
    /// both a refracted and a reflected child pushes, at most one entry per
    /// generation.
    pub fn stack_capacity(&self) -> u32 {
        if self.has_refraction { self.max_depth.max(1) } else { 1 }
    }
}
