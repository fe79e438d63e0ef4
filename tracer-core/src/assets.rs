//! Where a scene's files come from. Every loader (the scene's mesh objects,
//! an OBJ's `mtllib`, a glTF's buffers, PLY) reads through one
//! [`AssetSource`], by *name*: a '/'-separated path relative to the scene
//! file's folder, normalised by [`join`]. `tessera render` reads a local
//! folder ([`LocalFolder`]), the coordinator the job's stored bundle and a
//! worker its cache (both [`Bundle`]s): the same names and the same bytes
//! everywhere, so a scene cannot parse one way locally and another on the
//! farm, and its errors read the same.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// Why a file could not be read. Display names the file (by its name).
#[derive(Debug, thiserror::Error)]
pub enum AssetError {
    #[error("{name}: cannot read: {message}")]
    Io { name: String, message: String },
    #[error("{name}: is not a regular file")]
    NotAFile { name: String },
    #[error("{name}: is not among the job's files (the client did not send it)")]
    Missing { name: String },
    #[error("{name}: {size} bytes is over the limit of {limit} bytes a file")]
    TooLarge { name: String, size: u64, limit: u64 },
}

/// A scene's files by name. `Sync`: loaders may run on rayon threads.
pub trait AssetSource: Sync {
    /// The whole content of the file `name` (as made by [`join`]).
    fn read(&self, name: &str) -> Result<Arc<[u8]>, AssetError>;
}

/// `rel` (as written in a file whose own folder is `dir`, a name) as a
/// name: '/'-separated, `.` and `x/..` folded away. `..` above the scene's
/// folder stays as leading `../` segments and an absolute path stays
/// absolute (see [`leaves_folder`]). Backslashes count as separators
/// (models written on Windows).
pub fn join(dir: &str, rel: &str) -> String {
    let rel = rel.replace('\\', "/");
    let base = if rel.starts_with('/') { "" } else { dir };
    // Absolute when `rel` is, or when it is relative to an absolute folder
    // (the MTL or buffers of a model named by absolute path).
    let absolute = rel.starts_with('/') || base.starts_with('/');
    let mut parts: Vec<&str> = Vec::new();
    for seg in base.split('/').chain(rel.split('/')) {
        match seg {
            "" | "." => {}
            ".." => match parts.last() {
                Some(&p) if p != ".." => {
                    parts.pop();
                }
                _ if absolute => {}
                _ => parts.push(".."),
            },
            s => parts.push(s),
        }
    }
    let joined = parts.join("/");
    if absolute {
        format!("/{joined}")
    } else {
        joined
    }
}

/// The folder part of a name ("" for a file in the scene's folder).
pub fn dir_of(name: &str) -> &str {
    name.rsplit_once('/').map_or("", |(d, _)| d)
}

/// Whether a name lies outside the scene's folder (absolute, or `..` above it).
pub fn leaves_folder(name: &str) -> bool {
    name.starts_with('/') || name == ".." || name.starts_with("../")
}

/// Files on this machine's disk, names resolved against `root` (the scene
/// file's folder). Opens regular files only: a name that is a directory,
/// a FIFO or a device (`/dev/zero`) is an error, never a read that blocks
/// or never ends.
#[derive(Clone, Debug)]
pub struct LocalFolder {
    root: PathBuf,
}

impl LocalFolder {
    pub fn new(root: impl Into<PathBuf>) -> Self {
        LocalFolder { root: root.into() }
    }

    /// The folder of a scene file.
    pub fn of_scene(scene: &Path) -> Self {
        LocalFolder::new(scene.parent().unwrap_or(Path::new("")))
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.root.join(name)
    }
}

/// Reads a regular file whole; anything else is refused before it is opened.
pub fn read_regular_file(path: &Path, name: &str) -> Result<Vec<u8>, AssetError> {
    use std::io::Read as _;
    let io = |e: std::io::Error| AssetError::Io {
        name: name.to_string(),
        message: e.to_string(),
    };
    // Checked before opening: opening a FIFO for reading blocks until a writer comes.
    if !std::fs::metadata(path).map_err(io)?.is_file() {
        return Err(AssetError::NotAFile { name: name.into() });
    }
    let mut f = std::fs::File::open(path).map_err(io)?;
    let meta = f.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(AssetError::NotAFile { name: name.into() });
    }
    let mut data = Vec::new();
    data.try_reserve_exact(meta.len() as usize)
        .map_err(|_| AssetError::TooLarge {
            name: name.into(),
            size: meta.len(),
            limit: isize::MAX as u64,
        })?;
    // At most the size it had when opened (a file that grows is read as it was).
    f.by_ref()
        .take(meta.len())
        .read_to_end(&mut data)
        .map_err(io)?;
    Ok(data)
}

impl AssetSource for LocalFolder {
    fn read(&self, name: &str) -> Result<Arc<[u8]>, AssetError> {
        read_regular_file(&self.path(name), name).map(Arc::from)
    }
}

/// A job's files in memory, by name: what the coordinator validates a
/// submitted scene from and what a worker renders from. A name not in the
/// bundle is [`AssetError::Missing`]; nothing is read from any disk.
#[derive(Clone, Debug, Default)]
pub struct Bundle {
    files: BTreeMap<String, Arc<[u8]>>,
}

impl Bundle {
    pub fn new() -> Self {
        Bundle::default()
    }
    pub fn insert(&mut self, name: impl Into<String>, content: impl Into<Arc<[u8]>>) {
        self.files.insert(name.into(), content.into());
    }
    pub fn len(&self) -> usize {
        self.files.len()
    }
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }
}

impl AssetSource for Bundle {
    fn read(&self, name: &str) -> Result<Arc<[u8]>, AssetError> {
        self.files
            .get(name)
            .cloned()
            .ok_or_else(|| AssetError::Missing { name: name.into() })
    }
}

/// Remembers every file read through it, in order: how `tessera submit`
/// learns which files a scene needs (exactly those its loaders open).
pub struct Recorder<'a, S: AssetSource> {
    inner: &'a S,
    read: Mutex<Vec<(String, Arc<[u8]>)>>,
}

impl<'a, S: AssetSource> Recorder<'a, S> {
    pub fn new(inner: &'a S) -> Self {
        Recorder {
            inner,
            read: Mutex::new(Vec::new()),
        }
    }
    /// The files read, each once, in the order first read.
    pub fn into_files(self) -> Vec<(String, Arc<[u8]>)> {
        let mut files = self.read.into_inner().unwrap_or_else(|e| e.into_inner());
        let mut seen = std::collections::HashSet::new();
        files.retain(|(n, _)| seen.insert(n.clone()));
        files
    }
}

impl<S: AssetSource> AssetSource for Recorder<'_, S> {
    fn read(&self, name: &str) -> Result<Arc<[u8]>, AssetError> {
        let data = self.inner.read(name)?;
        self.read
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push((name.to_string(), data.clone()));
        Ok(data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_normalised_relative_to_the_scene_folder() {
        assert_eq!(join("", "models/x.obj"), "models/x.obj");
        assert_eq!(join("models", "x.mtl"), "models/x.mtl");
        assert_eq!(join("models", "./sub/../x.mtl"), "models/x.mtl");
        assert_eq!(join("models", "..\\tex\\y.bin"), "tex/y.bin");
        assert_eq!(join("", "../../m/b.ply"), "../../m/b.ply");
        assert_eq!(join("a", "../../b.ply"), "../b.ply");
        assert_eq!(join("a", "/abs/../m.obj"), "/m.obj");
        assert_eq!(join("", "/.."), "/");
        assert_eq!(join("/models/car", "car.bin"), "/models/car/car.bin");
        assert_eq!(join("/models/car", "../../../x.mtl"), "/x.mtl");
        assert!(leaves_folder("../b.ply") && leaves_folder("/m.obj") && leaves_folder(".."));
        assert!(!leaves_folder("models/x.obj") && !leaves_folder("..x.obj"));
        assert_eq!(dir_of("models/x.obj"), "models");
        assert_eq!(dir_of("x.obj"), "");
    }

    #[test]
    fn local_folders_read_regular_files_only() {
        let d = std::env::temp_dir().join(format!("tessera-assets-{}", std::process::id()));
        std::fs::create_dir_all(d.join("sub")).unwrap();
        std::fs::write(d.join("sub/a.obj"), b"v 0 0 0\n").unwrap();
        let src = LocalFolder::new(&d);
        assert_eq!(&*src.read("sub/a.obj").unwrap(), b"v 0 0 0\n");
        let e = src.read("sub").unwrap_err().to_string();
        assert_eq!(e, "sub: is not a regular file");
        let e = LocalFolder::new("/")
            .read("dev/zero")
            .unwrap_err()
            .to_string();
        assert_eq!(e, "dev/zero: is not a regular file");
        let e = src.read("absent.obj").unwrap_err().to_string();
        assert!(
            e.starts_with("absent.obj: cannot read: No such file"),
            "{e}"
        );
        let rec = Recorder::new(&src);
        rec.read("sub/a.obj").unwrap();
        rec.read("sub/a.obj").unwrap();
        assert!(rec.read("nope").is_err());
        let files = rec.into_files();
        assert_eq!(files.len(), 1);
        assert_eq!(files[0].0, "sub/a.obj");
        let mut b = Bundle::new();
        b.insert("x.ply", &b"ply"[..]);
        assert_eq!(&*b.read("x.ply").unwrap(), b"ply");
        assert_eq!(
            b.read("y.ply").unwrap_err().to_string(),
            "y.ply: is not among the job's files (the client did not send it)"
        );
    }
}
