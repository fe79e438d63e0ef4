//! The worker's in-memory caches: parsed scenes by content and prepared
//! frames by (job, frame), filled from the asset cache ([`crate::cache`])
//! or fetched from the coordinator.

use std::sync::Arc;
use std::time::Instant;

use tessera_proto::{LeasedJob, pb};
use tracer_core::assets::Bundle;
use tracer_core::render::{Precision, PreparedFrame};
use tracer_core::scene::SceneDesc;

use crate::cache;
use crate::{Client, PREPARED_CACHE, Worker};

impl Worker {
    /// The prepared frame `frame` of a unit's job, from cache or built
    /// from the (cached, content-addressed) scene.
    pub(crate) async fn prepare(
        &mut self,
        client: &mut Client,
        job: &LeasedJob,
        frame: u32,
    ) -> Result<Arc<PreparedFrame>, tonic::Status> {
        let key = (job.job_id.clone(), frame);
        if let Some((_, p)) = self.prepared.iter().find(|(k, _)| *k == key) {
            return Ok(p.clone());
        }
        // The scene and its files, by hash, from the cache or the
        // coordinator; parsed from those bytes only (never from this disk).
        let scene_key = std::iter::once(job.scene_sha256.as_str())
            .chain(job.files.iter().flat_map(|(n, h)| [n.as_str(), h.as_str()]))
            .collect::<Vec<_>>()
            .join("\n");
        let settings = job.settings;
        let cached = self
            .scenes
            .iter()
            .find(|(k, _)| *k == scene_key)
            .map(|(_, s)| s.clone());
        let scene = match cached {
            Some(scene) => scene,
            None => {
                let content = self.fetch(client, &job.scene_sha256).await?;
                let text = String::from_utf8(content).map_err(|e| {
                    tonic::Status::invalid_argument(format!(
                        "{}: scene is not UTF-8: {e}",
                        job.scene_name
                    ))
                })?;
                let mut bundle = Bundle::new();
                for (name, sha256) in &job.files {
                    bundle.insert(name.clone(), self.fetch(client, sha256).await?);
                }
                let scene_name = job.scene_name.clone();
                let scene = tokio::task::spawn_blocking(move || {
                    SceneDesc::parse_from(&text, &scene_name, &bundle)
                })
                .await
                .map_err(|e| tonic::Status::internal(e.to_string()))?
                .map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
                let scene = Arc::new(scene);
                // A big scene is not kept: its models (28 bytes a
                // triangle) are freed before its tree is built, as
                // `tessera render` frees them, and its next frame parses
                // its files again (from the asset cache: cheaper than the
                // build, and the prepared frames are cached anyway).
                if model_triangles(&scene) < tracer_core::world::GIVE_UP_TRIANGLES_FROM {
                    self.scenes.push_back((scene_key, scene.clone()));
                    if self.scenes.len() > PREPARED_CACHE {
                        self.scenes.pop_front();
                    }
                }
                scene
            }
        };
        // Held here alone (a big scene, not cached), the scene is consumed.
        let built = tokio::task::spawn_blocking(move || match Arc::try_unwrap(scene) {
            Ok(owned) => PreparedFrame::build_owned(owned, &settings, frame, Precision::F32),
            Err(shared) => PreparedFrame::build(&shared, &settings, frame, Precision::F32),
        })
        .await;
        let prepared = built
            .map_err(|e| tonic::Status::internal(e.to_string()))?
            .map_err(|e| tonic::Status::invalid_argument(e.to_string()))?;
        let prepared = Arc::new(prepared);
        self.prepared.push_back((key, prepared.clone()));
        if self.prepared.len() > PREPARED_CACHE {
            self.prepared.pop_front();
        }
        Ok(prepared)
    }

    /// A job file by hash: from the cache when its bytes still match,
    /// else streamed from the coordinator, checked and cached.
    pub(crate) async fn fetch(
        &self,
        client: &mut Client,
        sha256: &str,
    ) -> Result<Vec<u8>, tonic::Status> {
        let cache = self.cache.clone();
        let key = sha256.to_string();
        if let Some(data) = tokio::task::spawn_blocking(move || cache.get(&key))
            .await
            .map_err(|e| tonic::Status::internal(e.to_string()))?
        {
            return Ok(data);
        }
        let start = Instant::now();
        let mut stream = client
            .fetch_asset(pb::GetAssetRequest {
                sha256: sha256.to_string(),
            })
            .await?
            .into_inner();
        let mut data = Vec::new();
        let mut size = None;
        while let Some(chunk) = stream.message().await? {
            let declared = *size.get_or_insert(chunk.size);
            if chunk.offset != data.len() as u64
                || data.len() as u64 + chunk.data.len() as u64 > declared
            {
                return Err(tonic::Status::data_loss(format!(
                    "asset {sha256}: the coordinator sent a chunk out of order or past the declared {declared} bytes"
                )));
            }
            if data.is_empty() {
                // Bounded by what this machine can hold: an error, not an abort.
                data.try_reserve_exact(declared as usize).map_err(|_| {
                    tonic::Status::resource_exhausted(format!(
                        "asset {sha256} of {declared} bytes does not fit in this worker's memory"
                    ))
                })?;
            }
            data.extend_from_slice(&chunk.data);
        }
        let got = cache::sha256_hex(&data);
        if got != sha256 {
            // Transient as far as the worker can tell: the unit is retried.
            return Err(tonic::Status::data_loss(format!(
                "asset {sha256}: the {} bytes received hash to {got}",
                data.len()
            )));
        }
        tracing::info!(
            sha256,
            bytes = data.len(),
            seconds = start.elapsed().as_secs_f64(),
            "asset fetched"
        );
        let cache = self.cache.clone();
        let key = sha256.to_string();
        let data = tokio::task::spawn_blocking(move || {
            if let Err(e) = cache.put(&key, &data) {
                tracing::warn!(sha256 = %key, error = %e, "cannot cache a job file (rendering from memory)");
            }
            data
        })
        .await
        .map_err(|e| tonic::Status::internal(e.to_string()))?;
        Ok(data)
    }
}

/// Triangles of the scene's loaded models (as loaded, before placement).
fn model_triangles(scene: &SceneDesc) -> usize {
    scene
        .models()
        .iter()
        .flatten()
        .map(|m| m.triangles.len())
        .sum()
}
