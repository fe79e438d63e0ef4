//! Reading results back: waiting for a submission with a timeout, mapping
//! buffers, and the GPU resolve of sums to 8-bit sRGB or linear f32.

use std::sync::mpsc;

use wgpu::util::DeviceExt as _;

use super::layout::ResolveParams;
use super::{GpuError, GpuRenderer, Resolve, Resolver, SUBMISSION_TIMEOUT, entire, sized, wgsl};

impl Resolve {
    fn entry_point(self) -> &'static str {
        match self {
            Resolve::Srgb8 => "resolve_srgb8",
            Resolve::Linear => "resolve_linear",
        }
    }

    /// Bytes of a resolved image of `pixels`, rounded to whole 8-byte words
    /// so that it maps (`wgpu::MAP_ALIGNMENT`).
    pub(super) fn image_bytes(self, pixels: usize) -> u64 {
        let bytes = match self {
            // 3 words per 4 pixels.
            Resolve::Srgb8 => pixels.div_ceil(4) * 12,
            Resolve::Linear => pixels * 12,
        };
        (bytes as u64).next_multiple_of(8)
    }

    /// Invocations of its kernel per workgroup x pixels per invocation.
    fn pixels_per_group(self) -> usize {
        match self {
            Resolve::Srgb8 => 64 * 4,
            Resolve::Linear => 64,
        }
    }
}

impl GpuRenderer {
    /// Records the resolve of `sums` (a film of `pixels`, each of `n`
    /// samples: the GPU's films count the same samples in every pixel) to
    /// `to` and the image's copy to its read-back buffer; returns the
    /// locked resolver holding that buffer.
    pub(super) fn encode_resolve(
        &self,
        enc: &mut wgpu::CommandEncoder,
        sums: &wgpu::Buffer,
        sums_bytes: u64,
        pixels: usize,
        to: Resolve,
        n: u32,
    ) -> Result<std::sync::MutexGuard<'_, Option<Resolver>>, GpuError> {
        let mut guard = self
            .resolver
            .lock()
            .map_err(|_| GpuError::Device("resolver cache poisoned".into()))?;
        let bytes = to.image_bytes(pixels);
        if guard.as_ref().is_none_or(|r| r.image_bytes < bytes) {
            let old = guard.take();
            *guard = Some(self.create_resolver(bytes, old));
        }
        let r = guard.as_mut().expect("just set");
        if to == Resolve::Srgb8 && r.samples != Some(n) {
            let t: Vec<[u32; 2]> = crate::film::srgb8_thresholds(n)
                .iter()
                .map(|&s| [s as u32, (s >> 32) as u32])
                .collect();
            self.queue
                .write_buffer(&r.thresholds, 0, bytemuck::cast_slice(&t));
            r.samples = Some(n);
        }
        let pipeline = match to {
            Resolve::Srgb8 => &mut r.srgb8,
            Resolve::Linear => &mut r.linear,
        };
        if pipeline.is_none() {
            *pipeline = Some(self.resolve_pipeline(&r.module, &r.pipeline_layout, to));
        }
        let pipeline = pipeline.as_ref().expect("just set");
        self.queue.write_buffer(
            &r.params,
            0,
            bytemuck::bytes_of(&ResolveParams::new(pixels, n)),
        );
        let b = |name| wgsl::RESOLVE.binding(name);
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tessera resolve"),
            layout: &r.layout,
            entries: &[
                entire(b("params"), &r.params),
                sized(b("sums"), sums, sums_bytes),
                entire(b("thresholds"), &r.thresholds),
                entire(b("image"), &r.image),
            ],
        });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tessera resolve"),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &group, &[]);
            self.dispatch_groups(&mut pass, pixels.div_ceil(to.pixels_per_group()) as u32);
        }
        enc.copy_buffer_to_buffer(&r.image, 0, &r.image_read, 0, Some(bytes));
        Ok(guard)
    }

    /// Test hook: resolves `sums` (each pixel of `n` samples) to linear f32
    /// on the GPU, as [`GpuRenderer::render_as`] does for `Output::Linear` after tracing, so
    /// that the kernel can be checked against the host on crafted sums.
    #[doc(hidden)]
    pub fn resolve_linear_sums(
        &self,
        sums: &[[u64; 3]],
        n: u32,
    ) -> Result<Vec<[f32; 3]>, GpuError> {
        if sums.is_empty() {
            return Ok(Vec::new());
        }
        self.check_fault()?;
        let words: Vec<u32> = sums
            .iter()
            .flatten()
            .flat_map(|&s| [s as u32, (s >> 32) as u32])
            .collect();
        let buffer = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("sums to resolve"),
                contents: bytemuck::cast_slice(&words),
                usage: wgpu::BufferUsages::STORAGE,
            });
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tessera resolve test"),
            });
        let pixels = sums.len();
        let guard = self.encode_resolve(
            &mut enc,
            &buffer,
            (words.len() * 4) as u64,
            pixels,
            Resolve::Linear,
            n,
        )?;
        self.wait(self.queue.submit([enc.finish()]))?;
        let r = guard.as_ref().expect("made by encode_resolve");
        self.read_with(&r.image_read, Resolve::Linear.image_bytes(pixels), |b| {
            linear_pixels(b, pixels)
        })
    }

    /// The resolve pipelines' layout and module (kept from `old`, their
    /// pipelines too) with image buffers of `image_bytes`.
    pub(super) fn create_resolver(&self, image_bytes: u64, old: Option<Resolver>) -> Resolver {
        use wgpu::BufferUsages as U;
        let image = self.buffer("resolved image", image_bytes, U::STORAGE | U::COPY_SRC);
        let image_read = self.buffer(
            "resolved image read",
            image_bytes,
            U::MAP_READ | U::COPY_DST,
        );
        if let Some(old) = old {
            return Resolver {
                image_bytes,
                image,
                image_read,
                ..old
            };
        }
        let (layout, pipeline_layout, module) = self.compute_kernel(
            "tessera resolve",
            &wgsl::RESOLVE,
            wgsl::resolve_module(wgsl::FILES),
        );
        Resolver {
            module,
            pipeline_layout,
            layout,
            srgb8: None,
            linear: None,
            params: self.buffer(
                "resolve params",
                size_of::<ResolveParams>() as u64,
                U::UNIFORM | U::COPY_DST,
            ),
            thresholds: self.buffer("sRGB thresholds", 255 * 8, U::STORAGE | U::COPY_DST),
            samples: None,
            image_bytes,
            image,
            image_read,
        }
    }

    fn resolve_pipeline(
        &self,
        module: &wgpu::ShaderModule,
        layout: &wgpu::PipelineLayout,
        to: Resolve,
    ) -> wgpu::ComputePipeline {
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(to.entry_point()),
                layout: Some(layout),
                module,
                entry_point: Some(to.entry_point()),
                compilation_options: Default::default(),
                cache: self.pipeline_cache(),
            });
        if let Some(c) = &self.disk_cache {
            c.save();
        }
        pipeline
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
        self.read_after(buffer, bytes, None, f)
    }

    /// [`GpuRenderer::read_with`], waiting only for submission `after`
    /// (which last wrote `buffer`), not for later ones, where given.
    pub(super) fn read_after<R>(
        &self,
        buffer: &wgpu::Buffer,
        bytes: u64,
        after: Option<wgpu::SubmissionIndex>,
        f: impl FnOnce(&[u8]) -> R,
    ) -> Result<R, GpuError> {
        let (tx, rx) = mpsc::channel();
        buffer.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
            let _ = tx.send(r);
        });
        let r = self.device.poll(wgpu::PollType::Wait {
            submission_index: after,
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

/// The first `pixels` of a read-back linear image (f32 RGB, 12 bytes each).
pub(super) fn linear_pixels(bytes: &[u8], pixels: usize) -> Vec<[f32; 3]> {
    let mut v = vec![[0.0f32; 3]; pixels];
    bytemuck::cast_slice_mut::<[f32; 3], u8>(&mut v).copy_from_slice(&bytes[..pixels * 12]);
    v
}
