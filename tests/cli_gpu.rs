//! `tessera gpus` and `tessera render --backend gpu` as a user runs them.
//! Needs a wgpu adapter (lavapipe in CI); with CI=true a missing adapter
//! fails the tests, elsewhere they skip with a message.

use std::path::PathBuf;
use std::process::{Command, Output};

fn tessera() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tessera"))
}

fn run(cmd: &mut Command) -> (Output, String, String) {
    let out = cmd.output().expect("tessera runs");
    (
        out.clone(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// The first adapter line of `tessera gpus`, or None (skip) outside CI.
fn adapter() -> Option<String> {
    let (out, stdout, stderr) = run(tessera().arg("gpus"));
    if !out.status.success() {
        if std::env::var("CI").is_ok_and(|v| v == "true") {
            panic!("CI=true but `tessera gpus` found no adapter: {stderr}");
        }
        eprintln!("SKIPPING GPU CLI tests: {stderr}");
        return None;
    }
    let mut lines = stdout.lines();
    assert!(
        lines.next().is_some_and(|h| h.starts_with("index name")
            && h.contains("type")
            && h.contains("backend")
            && h.ends_with("driver")),
        "{stdout}"
    );
    let first = lines.next().expect("one adapter line").to_string();
    eprintln!("GPU CLI tests use adapter {first}");
    Some(first)
}

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tessera-cli-gpu-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn gpus_lists_index_name_type_backend_driver() {
    let Some(first) = adapter() else { return };
    let cols: Vec<&str> = first.split_whitespace().collect();
    assert_eq!(cols[0], "0", "{first}");
    assert!(
        ["Vulkan", "Metal", "Dx12"]
            .iter()
            .any(|b| first.contains(b)),
        "{first}"
    );
}

#[test]
fn render_backend_gpu_matches_the_cpu_image() {
    if adapter().is_none() {
        return;
    }
    let scene = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/resolution.toml");
    let dir = tmpdir("render");
    let mut imgs = vec![];
    for (name, extra) in [
        ("gpu", &["--backend", "gpu", "--adapter", "0"][..]),
        ("cpu", &["--precision", "f64"][..]),
    ] {
        let o = dir.join(format!("{name}.png"));
        let (out, stdout, stderr) = run(tessera()
            .arg("render")
            .arg(&scene)
            .arg("-o")
            .arg(&o)
            .args(["--width", "80", "--height", "60"])
            .args(extra));
        assert!(out.status.success(), "{stderr}");
        assert!(stdout.starts_with("80x60 4 spp depth 10"), "{stdout}");
        if name == "gpu" {
            assert!(
                stdout.contains(" gpu:") && stdout.contains("rays (primary 19200,"),
                "{stdout}"
            );
        }
        imgs.push(image::open(&o).unwrap().to_rgb8());
    }
    // 8-bit sRGB: GPU f32 against CPU f64 within 2 levels on 99% of the pixels
    // (silhouette samples may flip; see tracer-core/tests/gpu.rs for the tolerance).
    let off = imgs[0]
        .pixels()
        .zip(imgs[1].pixels())
        .filter(|(a, b)| a.0.iter().zip(b.0.iter()).any(|(x, y)| x.abs_diff(*y) > 2))
        .count();
    assert!(
        off * 100 <= 80 * 60,
        "{off} pixels differ by more than 2/255"
    );
}

#[test]
fn gpu_flags_are_checked() {
    if adapter().is_none() {
        return;
    }
    let scene = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/resolution.toml");
    let dir = tmpdir("flags");
    let o = dir.join("x.png");
    let cases: [(&[&str], &str); 3] = [
        (
            &["--backend", "gpu", "--precision", "f64"],
            "--backend gpu renders in f32 only",
        ),
        (
            &["--backend", "gpu", "--adapter", "no-such-gpu-xyz"],
            "no GPU adapter matches \"no-such-gpu-xyz\"; available: 0: ",
        ),
        (
            &["--adapter", "0"],
            "--adapter only applies to --backend gpu",
        ),
    ];
    for (args, want) in cases {
        let (out, _, stderr) = run(tessera()
            .arg("render")
            .arg(&scene)
            .arg("-o")
            .arg(&o)
            .args(["--width", "8", "--height", "6"])
            .args(args));
        assert_eq!(out.status.code(), Some(1), "{args:?}: {stderr}");
        assert!(stderr.contains(want), "{args:?}: {stderr}");
    }
    assert!(!o.exists(), "a refused render wrote an image");
}

/// Without XDG_RUNTIME_DIR (a headless server, CI, a container), listing
/// GPUs prints nothing on stderr: no "error: XDG_RUNTIME_DIR is invalid or
/// not set in the environment." from libwayland, which Mesa's Vulkan
/// device-select layer asks for the display's GPU.
#[test]
fn gpus_without_xdg_runtime_dir_prints_no_display_noise() {
    let Some(_) = adapter() else { return };
    for args in [&["gpus"][..], &["gpus", "--json"]] {
        let (out, stdout, stderr) = run(tessera().args(args).env_remove("XDG_RUNTIME_DIR"));
        assert!(out.status.success(), "{args:?}: {stderr}");
        assert!(!stdout.is_empty(), "{args:?}");
        assert_eq!(stderr, "", "{args:?}");
    }
}
