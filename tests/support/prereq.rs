//! What a test needs of the machine, decided in one place (issue 33): a
//! missing prerequisite FAILS the test, unless tests/optional.txt lists it as
//! optional. Even then it fails on CI (`CI=true`), which has everything. An
//! optional prerequisite that is missing makes the test "not run": said on
//! stderr, and appended to the file `TESSERA_NOT_RUN` names, from which
//! scripts/test prints the list of what did not run at the end.
//!
//! Shared by the test crates: tests/support/mod.rs and
//! tracer-core/tests/common/mod.rs include this file.
#![allow(dead_code)]

use std::io::Write;
use std::path::PathBuf;

/// The one list of optional prerequisites (a name a line, `#` comments).
const OPTIONAL: &str = include_str!("../optional.txt");

fn is_optional(prerequisite: &str) -> bool {
    OPTIONAL
        .lines()
        .map(|l| l.split('#').next().unwrap_or("").trim())
        .any(|name| name == prerequisite)
}

/// `what`'s value when the prerequisite is there; when it is not, a panic
/// naming it and why, or `None` (the caller returns: the test did not run)
/// for a prerequisite listed as optional outside CI.
pub fn require<T, E: std::fmt::Display>(prerequisite: &str, what: Result<T, E>) -> Option<T> {
    let why = match what {
        Ok(t) => return Some(t),
        Err(why) => why.to_string(),
    };
    // libtest names each test's thread after the test.
    let test = std::thread::current()
        .name()
        .filter(|n| *n != "main")
        .unwrap_or("this test")
        .to_string();
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    if ci || !is_optional(prerequisite) {
        panic!(
            "{test} needs {prerequisite}, which is missing: {why} ({})",
            if ci {
                "on CI every prerequisite is required"
            } else {
                "tests/optional.txt does not list it as optional"
            }
        );
    }
    eprintln!("NOT RUN: {test}: optional prerequisite {prerequisite} is missing: {why}");
    if let Some(path) = std::env::var_os("TESSERA_NOT_RUN") {
        let line = format!("{test}: {prerequisite}: {why}\n");
        // One append of one line: concurrent tests do not interleave.
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .and_then(|mut f| f.write_all(line.as_bytes()))
            .unwrap_or_else(|e| panic!("cannot record a test not run in {path:?}: {e}"));
    }
    None
}

/// The repository's root (the workspace holding Cargo.lock), from any of
/// its crates.
pub fn repo_root() -> PathBuf {
    let here = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    here.ancestors()
        .find(|d| d.join("Cargo.lock").is_file())
        .unwrap_or(here)
        .to_path_buf()
}

/// `../shared/<p>` beside the repository (or under `TESSERA_SHARED`), the
/// real assets of /work/shared: its absence fails the test, never skips it.
pub fn shared(p: &str) -> PathBuf {
    let root = std::env::var_os("TESSERA_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("../shared"));
    let path = root.join(p);
    assert!(
        path.exists(),
        "{} is missing: the shared assets (../shared beside the repository, or TESSERA_SHARED) are needed",
        path.display()
    );
    path
}
