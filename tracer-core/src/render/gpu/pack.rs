//! A render's sums packed on the GPU into the farm's compact layout
//! (`tessera_proto::film_codec`): a GPU worker reads back only those bytes
//! and sends them as they are.

use super::{GpuError, GpuRenderer, entire, sized, wgsl};
use crate::film::{RayCounts, Rect};

/// A render's sums in the compact layout: each R, G, B sum of each pixel
/// (row-major over `rect`) as its low `sum_bytes` bytes, little-endian,
/// where `sum_bytes` is the fewest bytes every sum needs (at least 1).
/// Every pixel has `samples` samples. The same bytes as
/// `tessera_proto::film_codec::pack` of [`GpuRenderer::render`]'s film.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PackedSums {
    pub rect: Rect,
    pub samples: u32,
    pub sum_bytes: u8,
    pub sums: Vec<u8>,
    pub rays: RayCounts,
    pub nonfinite: u64,
}

/// The packing pipelines and their buffers, made on first use (only farm
/// workers pack).
pub(super) struct Packer {
    measure: wgpu::ComputePipeline,
    pack: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    params: wgpu::Buffer,
    width: wgpu::Buffer,
    width_read: wgpu::Buffer,
    pixels: usize,
    packed: wgpu::Buffer,
    packed_read: wgpu::Buffer,
}

/// Bytes of the packed buffer for `pixels` at the widest sums (8 bytes):
/// 96 bytes per 4 pixels, whole 8-byte words so that it maps.
fn packed_capacity(pixels: usize) -> u64 {
    pixels.div_ceil(8) as u64 * 192
}

impl GpuRenderer {
    /// Records the packing of `sums` (a film of `pixels`) and the copies of
    /// its width and bytes to their read-back buffers; returns the locked
    /// packer holding them.
    pub(super) fn encode_pack(
        &self,
        enc: &mut wgpu::CommandEncoder,
        sums: &wgpu::Buffer,
        sums_bytes: u64,
        pixels: usize,
    ) -> Result<std::sync::MutexGuard<'_, Option<Packer>>, GpuError> {
        let mut guard = self
            .packer
            .lock()
            .map_err(|_| GpuError::Device("packer cache poisoned".into()))?;
        if guard.as_ref().is_none_or(|p| p.pixels < pixels) {
            let old = guard.take();
            *guard = Some(self.create_packer(pixels, old));
        }
        let p = guard.as_ref().expect("just set");
        self.queue.write_buffer(
            &p.params,
            0,
            bytemuck::cast_slice(&[pixels as u32, 0, 0, 0]),
        );
        let b = |name| wgsl::PACK.binding(name);
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera pack"),
            layout: &p.layout,
            entries: &[
                entire(b("params"), &p.params),
                sized(b("sums"), sums, sums_bytes),
                entire(b("width"), &p.width),
                entire(b("packed"), &p.packed),
            ],
        });
        enc.clear_buffer(&p.width, 0, None);
        // Two passes: every sum's width is known before any is packed.
        for (pipeline, invocations) in [(&p.measure, pixels), (&p.pack, pixels.div_ceil(4))] {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tessera pack"),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &group, &[]);
            // 64 invocations a workgroup.
            self.dispatch_groups(&mut pass, invocations.div_ceil(64) as u32);
        }
        enc.copy_buffer_to_buffer(&p.width, 0, &p.width_read, 0, Some(8));
        // The widest case: the width is only known on the GPU. Only the
        // bytes of the actual width are mapped and read.
        enc.copy_buffer_to_buffer(
            &p.packed,
            0,
            &p.packed_read,
            0,
            Some(packed_capacity(pixels)),
        );
        Ok(guard)
    }

    /// The width and the packed bytes of a film of `pixels`, once the
    /// submission that [`GpuRenderer::encode_pack`] recorded is done.
    pub(super) fn read_packed(&self, p: &Packer, pixels: usize) -> Result<(u8, Vec<u8>), GpuError> {
        let width: Vec<u32> = self.read(&p.width_read, 8)?;
        let w = width[0];
        if !(1..=8).contains(&w) {
            return Err(GpuError::Readback(format!(
                "the packed sums' width is {w} bytes, not 1 to 8"
            )));
        }
        let len = pixels * 3 * w as usize;
        let mapped = (len as u64).div_ceil(8) * 8;
        let bytes = self.read_with(&p.packed_read, mapped, |view| view[..len].to_vec())?;
        Ok((w as u8, bytes))
    }

    /// The packing pipelines (kept from `old`) with buffers for `pixels`.
    fn create_packer(&self, pixels: usize, old: Option<Packer>) -> Packer {
        use wgpu::BufferUsages as U;
        let packed = self.buffer(
            "packed sums",
            packed_capacity(pixels),
            U::STORAGE | U::COPY_SRC,
        );
        let packed_read = self.buffer(
            "packed sums read",
            packed_capacity(pixels),
            U::MAP_READ | U::COPY_DST,
        );
        if let Some(old) = old {
            return Packer {
                pixels,
                packed,
                packed_read,
                ..old
            };
        }
        let (layout, pipeline_layout, module) =
            self.compute_kernel("tessera pack", &wgsl::PACK, wgsl::pack_module(wgsl::FILES));
        let pipeline = |entry: &str| {
            self.device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("tessera pack"),
                    layout: Some(&pipeline_layout),
                    module: &module,
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    cache: self.pipeline_cache(),
                })
        };
        let (measure, pack) = (pipeline("measure"), pipeline("pack"));
        if let Some(c) = &self.disk_cache {
            c.save();
        }
        Packer {
            measure,
            pack,
            layout,
            params: self.buffer("pack params", 16, U::UNIFORM | U::COPY_DST),
            width: self.buffer("packed width", 8, U::STORAGE | U::COPY_SRC | U::COPY_DST),
            width_read: self.buffer("packed width read", 8, U::MAP_READ | U::COPY_DST),
            pixels,
            packed,
            packed_read,
        }
    }
}
