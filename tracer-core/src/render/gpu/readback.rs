//! Reading results back: waiting for a submission with a timeout, mapping
//! buffers, and the GPU resolve of sums to 8-bit sRGB.

use std::sync::mpsc;

use super::pipelines::RESOLVE_WGSL;
use super::{GpuError, GpuRenderer, Resolver, SUBMISSION_TIMEOUT, entire};
use crate::film::SampleRange;

impl GpuRenderer {
    /// Records the resolve of `sums` (a film of `pixels`, each of
    /// `samples.len()` samples) to 8-bit sRGB and the image's copy to its
    /// read-back buffer; returns the locked resolver holding that buffer.
    pub(super) fn encode_resolve(
        &self,
        enc: &mut wgpu::CommandEncoder,
        sums: &wgpu::Buffer,
        sums_bytes: u64,
        pixels: usize,
        samples: SampleRange,
    ) -> Result<std::sync::MutexGuard<'_, Option<Resolver>>, GpuError> {
        let mut guard = self
            .resolver
            .lock()
            .map_err(|_| GpuError::Device("resolver cache poisoned".into()))?;
        if guard.as_ref().is_none_or(|r| r.pixels < pixels) {
            let old = guard.take();
            *guard = Some(self.create_resolver(pixels, old));
        }
        let r = guard.as_mut().expect("just set");
        let n = samples.len();
        if r.samples != Some(n) {
            let t: Vec<[u32; 2]> = crate::film::srgb8_thresholds(n)
                .iter()
                .map(|&s| [s as u32, (s >> 32) as u32])
                .collect();
            self.queue
                .write_buffer(&r.thresholds, 0, bytemuck::cast_slice(&t));
            r.samples = Some(n);
        }
        self.queue.write_buffer(
            &r.params,
            0,
            bytemuck::cast_slice(&[pixels as u32, 0, 0, 0]),
        );
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera resolve"),
            layout: &r.layout,
            entries: &[
                entire(0, &r.params),
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: sums,
                        offset: 0,
                        size: wgpu::BufferSize::new(sums_bytes),
                    }),
                },
                entire(2, &r.thresholds),
                entire(3, &r.image),
            ],
        });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tessera resolve"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&r.pipeline);
            pass.set_bind_group(0, &group, &[]);
            // One invocation per 4 pixels, 64 a workgroup; rows of workgroups
            // past the per-dimension limit (an 8K film).
            let groups = pixels.div_ceil(4 * 64) as u32;
            let x = groups.min(self.device.limits().max_compute_workgroups_per_dimension);
            pass.dispatch_workgroups(x, groups.div_ceil(x), 1);
        }
        enc.copy_buffer_to_buffer(&r.image, 0, &r.image_read, 0, Some(image_bytes(pixels)));
        Ok(guard)
    }

    /// The resolve pipeline (kept from `old`) with image buffers for `pixels`.
    pub(super) fn create_resolver(&self, pixels: usize, old: Option<Resolver>) -> Resolver {
        use wgpu::BufferUsages as U;
        let image = self.buffer(
            "resolved image",
            image_bytes(pixels),
            U::STORAGE | U::COPY_SRC,
        );
        let image_read = self.buffer(
            "resolved image read",
            image_bytes(pixels),
            U::MAP_READ | U::COPY_DST,
        );
        if let Some(old) = old {
            return Resolver {
                pixels,
                image,
                image_read,
                ..old
            };
        }
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        use wgpu::BufferBindingType as B;
        let layout = self
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("tessera resolve"),
                entries: &[
                    entry(0, B::Uniform),
                    entry(1, B::Storage { read_only: true }),
                    entry(2, B::Storage { read_only: true }),
                    entry(3, B::Storage { read_only: false }),
                ],
            });
        let pipeline_layout = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("tessera resolve"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("resolve.wgsl"),
                source: wgpu::ShaderSource::Wgsl(RESOLVE_WGSL.into()),
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("tessera resolve"),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some("resolve_srgb8"),
                compilation_options: Default::default(),
                cache: self.pipeline_cache(),
            });
        if let Some(c) = &self.disk_cache {
            c.save();
        }
        Resolver {
            pipeline,
            layout,
            params: self.buffer("resolve params", 16, U::UNIFORM | U::COPY_DST),
            thresholds: self.buffer("sRGB thresholds", 255 * 8, U::STORAGE | U::COPY_DST),
            samples: None,
            pixels,
            image,
            image_read,
        }
    }

    /// Blocks until submission `index` is done, with a timeout, surfacing
    /// device loss and errors instead of hanging.
    pub(super) fn wait(&self, index: wgpu::SubmissionIndex) -> Result<(), GpuError> {
        let r = self.device.poll(wgpu::PollType::Wait {
            submission_index: Some(index),
            timeout: Some(SUBMISSION_TIMEOUT),
        });
        self.check_fault()?;
        match r {
            Ok(_) => Ok(()),
            Err(wgpu::PollError::Timeout) => Err(GpuError::Timeout(SUBMISSION_TIMEOUT)),
            Err(e) => Err(GpuError::Device(e.to_string())),
        }
    }

    pub(super) fn read<T: bytemuck::Pod>(
        &self,
        buffer: &wgpu::Buffer,
        bytes: u64,
    ) -> Result<Vec<T>, GpuError> {
        self.read_with(buffer, bytes, |view| {
            let mut v = vec![<T as bytemuck::Zeroable>::zeroed(); view.len() / size_of::<T>()];
            bytemuck::cast_slice_mut::<T, u8>(&mut v).copy_from_slice(view);
            v
        })
    }

    /// Maps the first `bytes` of `buffer` and hands them to `f`.
    pub(super) fn read_with<R>(
        &self,
        buffer: &wgpu::Buffer,
        bytes: u64,
        f: impl FnOnce(&[u8]) -> R,
    ) -> Result<R, GpuError> {
        let (tx, rx) = mpsc::channel();
        buffer.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
            let _ = tx.send(r);
        });
        let r = self.device.poll(wgpu::PollType::Wait {
            submission_index: None,
            timeout: Some(SUBMISSION_TIMEOUT),
        });
        self.check_fault()?;
        if let Err(e) = r {
            return Err(GpuError::Readback(e.to_string()));
        }
        match rx.recv_timeout(SUBMISSION_TIMEOUT) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(GpuError::Readback(e.to_string())),
            Err(_) => return Err(GpuError::Readback("mapping never completed".into())),
        }
        let out = {
            let view = buffer
                .get_mapped_range(0..bytes)
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            f(&view)
        };
        buffer.unmap();
        Ok(out)
    }
}

/// Bytes of a resolved image of `pixels`: 3 words per 4 pixels, rounded to
/// whole 8-byte words so that it maps (`wgpu::MAP_ALIGNMENT`).
pub(super) fn image_bytes(pixels: usize) -> u64 {
    pixels.div_ceil(8) as u64 * 24
}
