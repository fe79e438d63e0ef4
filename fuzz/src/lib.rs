//! Shared parts of Tessera's fuzz targets (see fuzz/README.md).
//!
//! * [`CappedAlloc`]: one allocation larger than [`MAX_ALLOCATION`] fails.
//!   An infallible allocation (`Vec::with_capacity`, `vec![..; n]`) then
//!   aborts ("memory allocation of N bytes failed"), which libFuzzer reports
//!   as a crash, while `try_reserve` gets an error it can report. Inputs are
//!   at most 64 KiB (`-max_len=65536`): a loader asking for this much
//!   believed a count in the file instead of checking it against the file's
//!   size. This is the fuzz build's malloc limit without a sanitizer.
//! * [`check_mesh`] / [`check_scene`]: a loader's "the model loader failed
//!   on this file" error is a panic that `Mesh::load_from` caught; issue 14
//!   wants malformed input rejected before a third-party crate panics, so
//!   the targets treat it as a finding and show the caught panic's message
//!   and place.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::{Mutex, Once};

use tracer_core::assets::Bundle;
use tracer_core::mesh::{Mesh, MeshError};

/// The largest single allocation a fuzz target may make (bytes).
pub const MAX_ALLOCATION: usize = 512 << 20;

pub struct CappedAlloc;

unsafe impl GlobalAlloc for CappedAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() > MAX_ALLOCATION {
            return std::ptr::null_mut();
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if layout.size() > MAX_ALLOCATION {
            return std::ptr::null_mut();
        }
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > MAX_ALLOCATION {
            return std::ptr::null_mut();
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOC: CappedAlloc = CappedAlloc;

/// What `Mesh::load_from` says when it caught a loader's panic.
pub const CAUGHT_PANIC: &str = "the model loader failed on this file";

/// The message and place of the last panic on this thread, even one that
/// the loaders' quiet `catch_unwind` hides.
static LAST_PANIC: Mutex<Option<String>> = Mutex::new(None);

/// Installs a panic hook that records every panic and then runs the hooks
/// before it (the loaders' quiet hook, then libFuzzer's abort). Mesh loading
/// runs once first so that the loaders' hook exists and ours wraps it.
/// Each target calls this first, for each input: it forgets the panics
/// recorded before.
pub fn init() {
    reset();
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // An existing file: the hook is installed when a loader first runs.
        let mut files = Bundle::new();
        files.insert("init.obj", &b""[..]);
        let _ = Mesh::load_from(&files, "init.obj", false);
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            *LAST_PANIC.lock().unwrap_or_else(|e| e.into_inner()) = Some(info.to_string());
            previous(info);
        }));
    });
}

/// A panic recorded during the call that gave `error` can only have been
/// caught (any other ends the process): a finding. The recorded panic, not
/// the error text, decides: a scene or model may quote the words of
/// [`CAUGHT_PANIC`] in its own error messages.
fn caught_panic(error: &str) {
    let panic = LAST_PANIC.lock().unwrap_or_else(|e| e.into_inner()).take();
    if let Some(panic) = panic {
        panic!("a loader panicked and the panic was caught: {error}\n  the panic: {panic}");
    }
}

/// Forgets any panic recorded before.
fn reset() {
    LAST_PANIC.lock().unwrap_or_else(|e| e.into_inner()).take();
}

/// A loaded mesh is fine and so is an error, unless it is a caught panic.
pub fn check_mesh(result: Result<Mesh, MeshError>) {
    match result {
        Ok(mesh) => {
            // What `validate` promises the renderer.
            let n = mesh.positions.len();
            assert!(!mesh.triangles.is_empty());
            assert!(mesh.triangles.iter().flatten().all(|&i| (i as usize) < n));
            assert_eq!(mesh.triangle_materials.len(), mesh.triangles.len());
            assert!(mesh.normals.is_empty() || mesh.normals.len() == n);
        }
        Err(e) => caught_panic(&e.to_string()),
    }
}

/// A scene error is fine unless it is a caught loader panic.
pub fn check_scene<T, E: std::fmt::Display>(result: Result<T, E>) {
    if let Err(e) = result {
        caught_panic(&e.to_string());
    }
}
