//! A scene and the files it references, gathered for the farm: read
//! through the same loaders `tessera render` uses (so the bundle holds
//! exactly the files a render opens), hashed, and uploaded to the
//! coordinator, only those it lacks, as chunks of at most 1 MiB.

use std::collections::BTreeMap;
use std::io::IsTerminal as _;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Result, bail};
use tessera_proto::pb;
use tessera_proto::transport::{ASSET_CHUNK_BYTES, sha256_hex};
use tracer_core::assets::{AssetError, AssetSource, LocalFolder, Recorder, join, leaves_folder};
use tracer_core::scene::{ModelSceneOptions, ObjectDesc, SceneDesc, SceneError, SceneInput};

use super::farm_common::{JobClient, rpc};

/// A scene file's text and its referenced files, by name.
pub struct SceneBundle {
    pub scene: Vec<u8>,
    pub files: Vec<BundleFile>,
}

pub struct BundleFile {
    pub name: String,
    pub sha256: String,
    pub content: Arc<[u8]>,
}

/// Reads and validates the scene at `path` with every file it references.
/// A model file given as the scene travels as the TOML scene `tessera
/// render` makes of it (`options`: `--camera` and the size flags), with the
/// model and its files. A file outside the scene's folder is refused,
/// naming the field, unless `allow_outside` (then it travels under the
/// name the scene gives it).
pub fn gather(
    path: &Path,
    options: &ModelSceneOptions,
    allow_outside: bool,
) -> Result<SceneBundle> {
    let scene = if SceneInput::of(path)? == SceneInput::Model || options.camera.is_some() {
        SceneDesc::input_text(path, options)?.into_bytes()
    } else {
        std::fs::read(path).map_err(|error| SceneError::Io {
            path: path.to_owned(),
            error,
        })?
    };
    let text = std::str::from_utf8(&scene)
        .map_err(|e| anyhow::anyhow!("{}: scene is not UTF-8 text: {e}", path.display()))?;
    let folder = Confined {
        inner: LocalFolder::of_scene(path),
        allow_outside,
        refused: std::sync::Mutex::new(None),
    };
    let recorder = Recorder::new(&folder);
    let parsed = SceneDesc::parse_input(text, path, &recorder, options);
    // A file outside the folder is refused before it is opened (an
    // absolute path such as /etc/passwd is never read), whatever the
    // loader then made of the refusal.
    let refused = folder
        .refused
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .take();
    if let (Some(name), Err(e)) = (&refused, &parsed) {
        let field = match e {
            // `objects[0] (mesh).path`, said as the other refusals say it.
            SceneError::Invalid { field, .. } if field.starts_with("objects[") => {
                field.split(']').next().unwrap_or_default().to_string() + "].path"
            }
            SceneError::Invalid { field, .. } if field == "world.environment" => field.clone(),
            SceneError::Input { message, .. } if message.starts_with("--environment") => {
                "--environment".into()
            }
            _ => "a file the scene's models refer to".into(),
        };
        bail!(
            "{}: {field}: {name:?} is outside the scene's folder, so the farm would not get it; \
             move it beside the scene, or pass --allow-outside to send a copy with the job",
            path.display()
        );
    }
    let desc = parsed?;
    // `--environment` on a TOML scene: the job's scene names the image.
    let scene = match &options.environment {
        Some(name) if SceneInput::of(path)? == SceneInput::Toml => {
            tracer_core::scene::with_environment(text, name)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
                .into_bytes()
        }
        _ => scene,
    };
    let files = recorder.into_files();
    for w in &desc.warnings {
        eprintln!("warning: {w}");
    }
    let outside = refused.or_else(|| {
        files
            .iter()
            .map(|(name, _)| name.clone())
            .find(|n| !allow_outside && leaves_folder(n))
    });
    if let Some(name) = outside {
        let field = desc.objects.iter().enumerate().find_map(|(i, o)| match o {
            ObjectDesc::Mesh(m) if join("", &m.path) == name => Some(format!("objects[{i}].path")),
            _ => None,
        });
        bail!(
            "{}: {}: {name:?} is outside the scene's folder, so the farm would not get it; \
             move it beside the scene, or pass --allow-outside to send a copy with the job",
            path.display(),
            field.unwrap_or_else(|| "a file the scene's models refer to".into())
        );
    }
    Ok(SceneBundle {
        scene,
        files: files
            .into_iter()
            .map(|(name, content)| BundleFile {
                sha256: sha256_hex(&content),
                name,
                content,
            })
            .collect(),
    })
}

/// The scene's folder, refusing (and remembering) the first name outside
/// it unless `allow_outside`: such a file is not opened at all.
struct Confined {
    inner: LocalFolder,
    allow_outside: bool,
    refused: std::sync::Mutex<Option<String>>,
}

impl AssetSource for Confined {
    fn read(&self, name: &str) -> Result<Arc<[u8]>, AssetError> {
        if !self.allow_outside && leaves_folder(name) {
            self.refused
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get_or_insert_with(|| name.to_string());
            return Err(AssetError::Io {
                name: name.to_string(),
                message: "outside the scene's folder (not read; --allow-outside sends it)".into(),
            });
        }
        self.inner.read(name)
    }
}

fn megabytes(b: u64) -> String {
    format!("{:.1} MB", b as f64 / 1e6)
}

/// Uploads the files the coordinator lacks; returns name -> sha256 for the
/// job spec. Says on stderr what it sent.
pub async fn upload(
    client: &mut JobClient,
    files: &[BundleFile],
) -> Result<BTreeMap<String, String>> {
    let names: BTreeMap<String, String> = files
        .iter()
        .map(|f| (f.name.clone(), f.sha256.clone()))
        .collect();
    if files.is_empty() {
        return Ok(names);
    }
    let missing = client
        .find_missing_assets(pb::FindMissingAssetsRequest {
            assets: files
                .iter()
                .map(|f| pb::AssetRef {
                    sha256: f.sha256.clone(),
                    size: f.content.len() as u64,
                })
                .collect(),
        })
        .await
        .map_err(rpc)?
        .into_inner()
        .missing;
    let start = Instant::now();
    let mut sent = 0u64;
    let mut uploaded = std::collections::HashSet::new();
    for f in files {
        if !missing.contains(&f.sha256) || !uploaded.insert(f.sha256.clone()) {
            continue;
        }
        let size = f.content.len() as u64;
        if std::io::stderr().is_terminal() {
            eprintln!("uploading {} ({})", f.name, megabytes(size));
        }
        let content = f.content.clone();
        let sha256 = f.sha256.clone();
        let chunks = size.div_ceil(ASSET_CHUNK_BYTES as u64).max(1);
        let stream = tokio_stream::iter((0..chunks).map(move |i| {
            let a = (i as usize) * ASSET_CHUNK_BYTES;
            let b = (a + ASSET_CHUNK_BYTES).min(content.len());
            pb::AssetChunk {
                sha256: if i == 0 {
                    sha256.clone()
                } else {
                    String::new()
                },
                size: if i == 0 { size } else { 0 },
                offset: a as u64,
                data: content[a..b].to_vec(),
            }
        }));
        let r = client
            .upload_asset(stream)
            .await
            .map_err(|s| anyhow::anyhow!("uploading {}: {}", f.name, rpc(s)))?
            .into_inner();
        sent += r.bytes_stored;
    }
    let total: u64 = files.iter().map(|f| f.content.len() as u64).sum();
    eprintln!(
        "files: {} ({}); uploaded {} ({}) in {:.2} s, {} already on the coordinator",
        files.len(),
        megabytes(total),
        uploaded.len(),
        megabytes(sent),
        start.elapsed().as_secs_f64(),
        files.len() - uploaded.len()
    );
    Ok(names)
}
