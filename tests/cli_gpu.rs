//! `tessera gpus` and `tessera render --backend gpu` as a user runs them.
//! Needs a wgpu adapter (lavapipe): the prerequisite `gpu`, whose absence
//! fails the tests (tests/support/prereq.rs).

use std::path::PathBuf;
use std::process::{Command, Output};
use tracer_core::film::WorkRegion;

mod support;

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

/// The first adapter line of `tessera gpus` (a missing adapter fails the test).
fn adapter() -> Option<String> {
    let stdout = support::gpus()?;
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

/// `tessera render --backend gpu -o x.exr` resolves on the GPU and reads
/// back only the f32 image: its file is the same bytes as the EXR of the
/// sums path (the GPU's film resolved on the host, as the farm does), and
/// its floats are those of the host's resolve bit for bit. Odd sizes, and
/// a sample count whose reciprocal is not a power of 2.
#[cfg(feature = "gpu")]
#[test]
fn render_backend_gpu_to_exr_equals_the_sums_path() {
    use tracer_core::film::{Rect, SampleRange};
    use tracer_core::render::gpu::{GpuOptions, GpuRenderer};
    use tracer_core::render::{Precision, PreparedFrame};
    use tracer_core::scene::{RenderSettings, SceneDesc};
    if adapter().is_none() {
        return;
    }
    let dir = tmpdir("exr");
    let gpu = GpuRenderer::new(Some("0"), GpuOptions::default()).unwrap();
    for (scene, width, height, samples) in
        [("resolution.toml", 61, 37, 3), ("cornell.toml", 33, 29, 7)]
    {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("examples")
            .join(scene);
        let exr = dir.join("gpu.exr");
        let (out, stdout, stderr) = run(tessera()
            .arg("render")
            .arg(&path)
            .arg("-o")
            .arg(&exr)
            .args(["--backend", "gpu", "--adapter", "0"])
            .args([
                "--width",
                &width.to_string(),
                "--height",
                &height.to_string(),
            ])
            .args(["--samples", &samples.to_string()]));
        assert!(out.status.success(), "{scene}: {stderr}");
        assert!(
            stdout.starts_with(&format!("{width}x{height} {samples} spp")),
            "{scene}: {stdout}"
        );

        let desc = SceneDesc::load(&path).unwrap();
        let settings = RenderSettings {
            width,
            height,
            samples,
            ..desc.render
        };
        let prepared = PreparedFrame::build(&desc, &settings, 0, Precision::F32).unwrap();
        let film = gpu
            .render(
                &prepared,
                WorkRegion::new(0, Rect::full(width, height), SampleRange::all(samples)),
                &|_| {},
            )
            .unwrap();
        let linear = film.resolve();
        let sums_exr = dir.join("sums.exr");
        tracer_core::film::image::write_exr(&sums_exr, width, height, &linear).unwrap();
        assert!(
            std::fs::read(&exr).unwrap() == std::fs::read(&sums_exr).unwrap(),
            "{scene}: the EXR differs from the sums path's"
        );

        let img = exr::prelude::read_first_flat_layer_from_file(&exr).unwrap();
        for (c, name) in ["R", "G", "B"].into_iter().enumerate() {
            let values = img
                .layer_data
                .channel_data
                .list
                .iter()
                .find(|ch| ch.name.to_string() == name)
                .map(|ch| match &ch.sample_data {
                    exr::prelude::FlatSamples::F32(v) => v.clone(),
                    other => panic!("{scene} {name}: {other:?}"),
                })
                .unwrap_or_else(|| panic!("{scene}: no {name} channel"));
            let host: Vec<f32> = linear.iter().map(|p| p[c]).collect();
            assert!(
                values
                    .iter()
                    .map(|v| v.to_bits())
                    .eq(host.iter().map(|v| v.to_bits())),
                "{scene} {name}: the EXR's floats are not the host's resolve"
            );
        }
    }
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
