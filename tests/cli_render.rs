//! `tessera render` as a user runs it: the real binary, real files, exit codes.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod support;
use support::shared;

fn tessera() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tessera"))
}

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tessera-cli-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run(cmd: &mut Command) -> (Output, String, String) {
    let out = cmd.output().expect("tessera runs");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    (out, stdout, stderr)
}

const GOOD: &str = r#"
[render]
width = 40
height = 30
samples = 1
[camera]
position = [0, 1, -6]
look_at = [0, 1, 0]
[materials.red]
diffuse = [1, 0, 0]
[[lights]]
position = [0, 5, -5]
[[objects]]
type = "sphere"
center = [0, 1, 0]
radius = 1
material = "red"
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "red"
"#;

#[test]
fn renders_png_and_exr_with_a_summary_line() {
    let dir = tmpdir("ok");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, GOOD).unwrap();
    // Default output: the scene's name with .png.
    let (out, stdout, stderr) = run(tessera().arg("render").arg(&scene).args(["--samples", "4"]));
    assert!(out.status.success(), "{stderr}");
    let png = image::open(dir.join("scene.png")).unwrap();
    assert_eq!((png.width(), png.height()), (40, 30));
    assert!(stdout.starts_with("40x30 4 spp depth 10 f32"), "{stdout}");
    assert!(
        stdout.contains("rays (primary 4800,") && stdout.contains("Mrays/s"),
        "{stdout}"
    );

    let exr = dir.join("out.exr");
    let (out, _, stderr) = run(tessera()
        .arg("render")
        .arg(&scene)
        .arg("-o")
        .arg(&exr)
        .args(["--width", "20", "--height", "10", "--precision", "f64"]));
    assert!(out.status.success(), "{stderr}");
    let img = image::open(&exr).unwrap().to_rgb32f();
    assert_eq!(img.dimensions(), (20, 10));
    // Linear float: the lit sphere is pure red, in [0, 1] here, and finite everywhere.
    assert!(img.pixels().all(|p| p.0.iter().all(|c| c.is_finite())));
    assert!(img.pixels().any(|p| p.0[0] > 0.5 && p.0[1] == 0.0));
}

fn expect_failure(scene_src: &str, args: &[&str], want: &[&str]) {
    let dir = tmpdir(&format!("bad{}", want[0].len() * 31 + scene_src.len()));
    let scene = dir.join("bad.toml");
    std::fs::write(&scene, scene_src).unwrap();
    let (out, stdout, stderr) = run(tessera()
        .arg("render")
        .arg(&scene)
        .args(args)
        .current_dir(&dir));
    assert!(
        !out.status.success(),
        "expected failure, got success: {stdout}"
    );
    assert_eq!(out.status.code(), Some(1));
    for w in want {
        assert!(stderr.contains(w), "stderr lacks {w:?}:\n{stderr}");
    }
    assert!(
        !Path::new(&dir.join("bad.png")).exists(),
        "no image is written on error"
    );
}

#[test]
fn an_example_whose_model_is_elsewhere_says_where_to_get_it() {
    // bunny.toml read from a folder with no ../shared beside it, as a
    // newcomer's checkout without the shared models.
    let src = std::fs::read_to_string(repo().join("examples/stanford/bunny.toml")).unwrap();
    expect_failure(
        &src,
        &[],
        &[
            "objects[0] (mesh).path: cannot load model: ../../../shared/meshes/stanford-bunny.obj: cannot read model file",
            "(the scene says the model comes from: github.com/alecjacobson/common-3d-test-models data/stanford-bunny.obj",
        ],
    );
}

#[test]
fn malformed_scenes_are_rejected_with_file_line_and_reason() {
    expect_failure(
        &GOOD.replace("[camera]", "[camera"),
        &[],
        &["bad.toml:6:8: unclosed table", "error: "],
    );
    expect_failure(
        &GOOD.replace("radius = 1", "radius = \"one\""),
        &[],
        &[
            "bad.toml:16:10: objects[0] (sphere).radius: invalid type: string \"one\", expected a number",
        ],
    );
    expect_failure(
        &GOOD.replace("radius = 1", "radius = 1\nshiny = true"),
        &[],
        &[
            "bad.toml:17:1: objects[0] (sphere).shiny: unknown field `shiny` (valid: `center`, `radius`, `material`, `keyframes`)",
        ],
    );
    expect_failure(
        &GOOD.replace(
            "material = \"red\"\n[[objects]]",
            "material = \"chrome\"\n[[objects]]",
        ),
        &[],
        &[
            "bad.toml:17:1: objects[0] (sphere).material: unknown material \"chrome\"; defined materials: red",
        ],
    );
    expect_failure(
        &GOOD.replace("radius = 1", "radius = -2"),
        &[],
        &["bad.toml:16:1: objects[0] (sphere).radius: must be a finite number > 0, got -2"],
    );
    expect_failure(
        &GOOD.replace("normal = [0, 1, 0]", "normal = [0, 0, 0]"),
        &[],
        &["bad.toml:20:1: objects[1] (plane).normal: must be a finite, non-zero vector"],
    );
    expect_failure(
        &GOOD.replace("radius = 1", "radius = nan"),
        &[],
        &["objects[0] (sphere).radius: must be a finite number > 0, got NaN"],
    );
    expect_failure(
        &GOOD.replace("position = [0, 5, -5]", "position = [0, inf, -5]"),
        &[],
        &["bad.toml:12:1: lights[0].position: must be finite"],
    );
    expect_failure(
        &GOOD.replace("look_at = [0, 1, 0]", "look_at = [0, 1, -6]"),
        &[],
        &["camera.look_at: must differ from the camera position"],
    );
    expect_failure(
        &GOOD.replace("samples = 1", "samples = 0"),
        &[],
        &["bad.toml:5:1: render.samples: must be in 1..=65536, got 0"],
    );
}

#[test]
fn bad_arguments_and_files_are_reported() {
    expect_failure(
        GOOD,
        &["-o", "x.jpg"],
        &["unsupported output extension .jpg"],
    );
    // Each cause once: the OS error is not repeated as the error's source.
    let (out, _, stderr) = run(tessera().args(["render", "/nonexistent/scene.toml"]));
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(
        stderr,
        "error: /nonexistent/scene.toml: cannot read scene: No such file or directory (os error 2)\n"
    );
    // clap's own usage errors exit with 2.
    let (out, _, stderr) = run(tessera().args(["render", "x.toml", "--precision", "f16"]));
    assert_eq!(out.status.code(), Some(2), "{stderr}");
}

/// Out-of-range numbers are refused before anything runs, with the range
/// the renderer really accepts (the scene format's limits), not the
/// integer type's.
#[test]
fn numeric_flags_state_their_real_ranges() {
    let cases: [(&str, &str, &str); 9] = [
        ("--samples", "0", "1..=65536"),
        ("--samples", "70000", "1..=65536"),
        ("--samples", "-1", "1..=65536"),
        ("--width", "0", "1..=32768"),
        ("--height", "40000", "1..=32768"),
        ("--max-depth", "65", "0..=64"),
        ("--threads", "5000", "0..=4096"),
        ("--width", "-3", "1..=32768"),
        ("--max-depth", "-1", "0..=64"),
    ];
    for (flag, value, range) in cases {
        let (out, _, stderr) = run(tessera().args(["render", "x.toml", flag, value]));
        assert_eq!(out.status.code(), Some(2), "{flag} {value}: {stderr}");
        let name = flag
            .trim_start_matches("--")
            .to_uppercase()
            .replace('-', "_");
        let want = format!(
            "error: invalid value '{value}' for '{flag} <{name}>': {value} is not in {range}"
        );
        assert_eq!(stderr.lines().next(), Some(want.as_str()), "{stderr}");
    }
    // The help says the same ranges, and what --frame does besides seeding.
    let (out, help, _) = run(tessera().args(["render", "--help"]));
    assert!(out.status.success());
    for text in [
        "Samples per pixel, 1..=65536",
        "Image width in pixels, 1..=32768",
        "Image height in pixels, 1..=32768",
        "secondary (reflected/refracted) rays, 0..=64",
        "0..=4096; 0 means all cores",
        "picks the camera's pose from the scene's [[camera.keyframes]]",
        "seeds the jittered sampler",
    ] {
        assert!(help.contains(text), "help lacks {text:?}:\n{help}");
    }
}

#[test]
fn threads_flag_gives_the_same_image() {
    let scene = repo().join("examples/resolution.toml");
    let dir = tmpdir("threads");
    let mut imgs = vec![];
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    // 0 means every core; the summary (as JSON) names the threads used.
    for (t, used) in [("1", 1), ("2", 2), ("0", cores)] {
        let o = dir.join(format!("t{t}.png"));
        let (out, stdout, stderr) = run(tessera()
            .arg("render")
            .arg(&scene)
            .arg("-o")
            .arg(&o)
            .args(["--width", "64", "--height", "48", "--threads", t, "--json"]));
        assert!(out.status.success(), "{stderr}");
        let summary: serde_json::Value = serde_json::from_str(&stdout).expect("JSON summary");
        assert_eq!(summary["renderer"], format!("cpu:{used}t"), "--threads {t}");
        assert_eq!(summary["rays"]["primary"], 64 * 48 * 4, "--threads {t}");
        imgs.push(std::fs::read(&o).unwrap());
    }
    assert_eq!(imgs[0], imgs[1], "thread count changed the image");
    assert_eq!(imgs[0], imgs[2], "thread count changed the image");
}

/// Model files made to hurt, each rendered by a real `tessera render` under
/// a 4 GB address-space cap: each ends at once with exit 1 and a message
/// naming the file and the problem, never an abort, a hang or panic text.
#[test]
fn hostile_model_files_end_in_a_clear_error_under_a_4_gb_cap() {
    use base64::Engine as _;
    let dir = tmpdir("hostile");
    let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
    let data_uri = |b: &[u8]| {
        format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(b)
        )
    };
    let gltf_view = |accessor: &str, uri: &str, view: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":36,"uri":"{uri}"}}],
            "bufferViews":[{view}],"accessors":[{accessor}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}]}}"#
        )
    };
    let gltf = |accessor: &str, uri: &str, _len: usize| {
        gltf_view(accessor, uri, r#"{"buffer":0,"byteLength":36}"#)
    };
    let vec3 = r#""componentType":5126,"type":"VEC3","min":[0,0,0],"max":[1,1,0]"#;
    let fifo = dir.join("pipe.bin");
    let made = Command::new("mkfifo").arg(&fifo).status().expect("mkfifo");
    assert!(made.success());
    // (file, content, expected exit code, text expected on stderr)
    let cases: Vec<(&str, String, i32, &str)> = vec![
        // A library that is no file: the default material, and a warning.
        (
            "zero.obj",
            format!("mtllib /dev/zero\n{tri}usemtl m\nf 1 2 3\n"),
            0,
            "zero.obj.toml: objects[0] (mesh).path: zero.obj: cannot load its material library (mtllib /dev/zero)",
        ),
        (
            "sparse.gltf",
            gltf(&format!(r#"{{{vec3},"count":4294967295,"sparse":{{"count":4294967295,"indices":{{"bufferView":0,"componentType":5125}},"values":{{"bufferView":0}}}}}}"#), &data_uri(&[0; 36]), 36),
            1,
            "sparse.gltf: mesh 0 primitive 0: accessor 0: 4294967295 elements without data",
        ),
        (
            "stride.gltf",
            gltf_view(
                &format!(r#"{{{vec3},"bufferView":0,"count":3}}"#),
                &data_uri(&[0; 36]),
                r#"{"buffer":0,"byteLength":36,"byteStride":4}"#,
            ),
            1,
            "stride.gltf: mesh 0 primitive 0: accessor 0: byteStride 4 is smaller than its 12-byte elements",
        ),
        ("fifo.gltf", gltf(&format!(r#"{{{vec3},"bufferView":0,"count":3}}"#), "pipe.bin", 36), 1, "fifo.gltf: cannot read buffer 0: pipe.bin: is not a regular file"),
        ("devzero.gltf", gltf(&format!(r#"{{{vec3},"bufferView":0,"count":3}}"#), "/dev/zero", 36), 1, "devzero.gltf: cannot read buffer 0: /dev/zero: is not a regular file"),
        (
            "huge.ply",
            "ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n".into(),
            1,
            "huge.ply: invalid PLY: vertex 0:",
        ),
        ("hot.obj", format!("mtllib hot.mtl\n{tri}usemtl h\nf 1 2 3\n"), 1, "hot.obj: material \"h\": ambient must be three finite numbers >= 0 and at most 1e6"),
    ];
    std::fs::write(dir.join("hot.mtl"), "newmtl h\nKd 1e39 1 1\n").unwrap();
    for (file, content, code, want) in cases {
        std::fs::write(dir.join(file), content).unwrap();
        let scene = dir.join(format!("{file}.toml"));
        std::fs::write(
            &scene,
            format!(
                "[render]\nwidth = 8\nheight = 8\nsamples = 1\n[camera]\nposition = [0, 0, 3]\nlook_at = [0, 0, 0]\n\
                 [[lights]]\nposition = [0, 1, 2]\n[[objects]]\ntype = \"mesh\"\npath = \"{file}\"\n"
            ),
        )
        .unwrap();
        let start = std::time::Instant::now();
        let (out, _, stderr) = run(Command::new("sh")
            .arg("-c")
            .arg("ulimit -v 4194304 && exec \"$0\" render \"$1\" -o \"$2\"")
            .arg(env!("CARGO_BIN_EXE_tessera"))
            .arg(&scene)
            .arg(dir.join(format!("{file}.png"))));
        let took = start.elapsed();
        assert_eq!(out.status.code(), Some(code), "{file}: {stderr}");
        assert!(
            stderr.contains(want),
            "{file}: expected {want:?} in {stderr}"
        );
        assert!(!stderr.contains("panicked"), "{file}: panic text: {stderr}");
        assert!(
            took < std::time::Duration::from_secs(10),
            "{file}: {took:?}"
        );
    }
}

/// A misspelt key in every table and array of tables of the format is
/// reported at its own line, with its full path and a suggestion.
#[test]
fn a_typo_in_any_table_is_located_at_its_key_with_a_suggestion() {
    let cases: [(&str, &str, &str); 8] = [
        (
            "width = 40",
            "widht = 40",
            "bad.toml:3:1: render.widht: unknown field `widht`; did you mean `width`?",
        ),
        (
            "look_at = [0, 1, 0]",
            "lookat = [0, 1, 0]",
            "bad.toml:8:1: camera.lookat: unknown field `lookat`; did you mean `look_at`?",
        ),
        (
            "[materials.red]",
            "[[camera.keyframes]]\nframe = 1\nfovy = 30\n[materials.red]",
            "bad.toml:11:1: camera.keyframes[0].fovy: unknown field `fovy`; did you mean `fov_y`?",
        ),
        (
            "[materials.red]",
            "[world]\nambeint = [0.1, 0.1, 0.1]\n[materials.red]",
            "bad.toml:10:1: world.ambeint: unknown field `ambeint`; did you mean `ambient`?",
        ),
        (
            "diffuse = [1, 0, 0]",
            "difuse = [1, 0, 0]",
            "bad.toml:10:1: materials.red.difuse: unknown field `difuse`; did you mean `diffuse`?",
        ),
        (
            "position = [0, 5, -5]",
            "position = [0, 5, -5]\ncolour = [1, 1, 1]",
            "bad.toml:13:1: lights[0].colour: unknown field `colour` (valid: `type`, `position`, `corner`, `edge_u`, `edge_v`, `center`, `radius`, `samples`, `direction`, `cone_angle`, `inner_cone_angle`, `diffuse`, `specular`)",
        ),
        (
            // Equally close to `sampler`: the plural of what was typed wins.
            "width = 40",
            "width = 40\nsample = 4",
            "bad.toml:4:1: render.sample: unknown field `sample`; did you mean `samples`?",
        ),
        (
            "distance = 0",
            "distnce = 0",
            "bad.toml:21:1: objects[1] (plane).distnce: unknown field `distnce`; did you mean `distance`?",
        ),
    ];
    for (from, to, want) in cases {
        assert!(GOOD.contains(from), "{from}");
        expect_failure(&GOOD.replacen(from, to, 1), &[], &[want]);
    }
}

/// `--target-error`: the EXR gains `samples` and `error` channels (each
/// pixel's count on the round schedule, never above --max-samples; a
/// finite error estimate), `--sample-map` writes a PNG of the image's
/// size, and every inconsistent combination of flags is refused by name.
#[test]
fn adaptive_renders_write_sample_and_error_channels_and_a_sample_map() {
    let dir = tmpdir("adaptive");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, GOOD).unwrap();
    // The same adaptive settings for both renders below.
    let adaptive = [
        "--target-error",
        "0.01",
        "--min-samples",
        "4",
        "--max-samples",
        "16",
    ];
    let (out, stdout, stderr) = run(tessera().arg("render").arg(&scene).args(adaptive).args([
        "-o",
        dir.join("a.exr").to_str().unwrap(),
        "--sample-map",
        dir.join("map.png").to_str().unwrap(),
    ]));
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.contains("adaptive: target error 0.01 (4..16 spp)"),
        "{stdout}"
    );
    assert!(stderr.contains("round 0 (samples 0..4)"), "{stderr}");
    let img = exr::prelude::read_first_flat_layer_from_file(dir.join("a.exr")).unwrap();
    let channel = |name: &str| -> Vec<f32> {
        let c = img
            .layer_data
            .channel_data
            .list
            .iter()
            .find(|c| c.name.to_string() == name)
            .unwrap_or_else(|| panic!("no {name} channel"));
        match &c.sample_data {
            exr::prelude::FlatSamples::F32(v) => v.clone(),
            other => panic!("{name}: {other:?}"),
        }
    };
    let samples = channel("samples");
    assert_eq!(samples.len(), 40 * 30);
    assert!(
        samples.iter().all(|&n| [4.0, 8.0, 16.0].contains(&n)),
        "{samples:?}"
    );
    assert!(samples.contains(&4.0) && samples.contains(&16.0));
    assert!(channel("error").iter().all(|e| e.is_finite() && *e >= 0.0));
    assert_eq!(channel("R").len(), 40 * 30);
    let map = image::open(dir.join("map.png")).unwrap();
    assert_eq!((map.width(), map.height()), (40, 30));
    // The same render's --json: the per-pixel mode's keys, its sample
    // count the EXR's.
    let (out, stdout, stderr) = run(tessera().arg("render").arg(&scene).args(adaptive).args([
        "-o",
        dir.join("b.exr").to_str().unwrap(),
        "--json",
    ]));
    assert!(out.status.success(), "{stderr}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let a = &v["adaptive"];
    assert_eq!(a["mode"], "pixel", "{stdout}");
    assert_eq!(
        (a["min_samples"].as_u64(), a["max_samples"].as_u64()),
        (Some(4), Some(16))
    );
    let total: f64 = samples.iter().map(|&n| n as f64).sum();
    assert_eq!(a["pixel_samples"].as_f64(), Some(total), "{stdout}");
    assert_eq!(
        a["mean_samples"].as_f64(),
        Some(total / (40.0 * 30.0)),
        "{stdout}"
    );
    assert_eq!(a["rounds"].as_u64(), Some(3), "{stdout}");
    let share = a["converged_share"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&share), "{stdout}");
    assert!(a["estimated_rms_error"].as_f64().unwrap() > 0.0, "{stdout}");
    assert!(a.get("target_rms_error").is_none(), "{stdout}");

    for (args, want) in [
        (
            &["--target-error", "0"][..],
            "target_error must be a finite number above 0, got 0",
        ),
        (
            &["--target-error", "-1"][..],
            "target_error must be a finite number above 0, got -1",
        ),
        (
            &["--relative-error", "0"][..],
            "relative_error must be a finite number above 0, got 0",
        ),
        (
            &["--relative-error", "NaN", "--target-error", "0.01"][..],
            "relative_error must be a finite number above 0, got NaN",
        ),
        (
            &[
                "--target-error",
                "0.01",
                "--min-samples",
                "64",
                "--max-samples",
                "32",
            ][..],
            "min_samples (64) must not exceed max_samples (32)",
        ),
        (
            &["--target-error", "0.01", "--min-samples", "1"][..],
            "min_samples must be at least 2",
        ),
        (
            &["--target-error", "0.01", "--samples", "8"][..],
            "--samples does not apply to adaptive sampling",
        ),
        (
            &["--target-error", "0.01", "--sampler", "grid"][..],
            "--sampler grid does not apply to adaptive sampling",
        ),
        (&["--min-samples", "8"][..], "give --target-error"),
        (
            &["--sample-map", "m.png"][..],
            "--sample-map applies to adaptive renders",
        ),
        (
            &["--adaptive-mode", "image"][..],
            "--adaptive-mode image needs a target",
        ),
    ] {
        expect_failure(GOOD, args, &[want]);
    }
}

/// `--adaptive-mode image` stops at the image's estimated RMSE and says
/// so: the JSON's estimate is within its target, the mean count inside
/// the flags' range and not uniform (the cheapest allocation differs by
/// block), and the picture is the scene's.
#[test]
fn the_image_rmse_mode_stops_at_its_target_and_reports_it() {
    let dir = tmpdir("adaptive-image");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, GOOD).unwrap();
    let exr = dir.join("i.exr");
    let (out, stdout, stderr) = run(tessera().arg("render").arg(&scene).args([
        "--target-error",
        "0.004",
        "--min-samples",
        "4",
        "--max-samples",
        "256",
        "--adaptive-mode",
        "image",
        "--json",
        "-o",
        exr.to_str().unwrap(),
    ]));
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("estimated image RMSE"), "{stderr}");
    let v: serde_json::Value = serde_json::from_str(&stdout).expect("json");
    let a = &v["adaptive"];
    assert_eq!(a["mode"], "image", "{stdout}");
    let (est, target) = (
        a["estimated_rms_error"].as_f64().unwrap(),
        a["target_rms_error"].as_f64().unwrap(),
    );
    assert_eq!(target, 0.004, "{stdout}");
    assert!(est > 0.0 && est <= target, "{stdout}");
    let mean = a["mean_samples"].as_f64().unwrap();
    assert!((4.0..256.0).contains(&mean), "{stdout}");
    let img = exr::prelude::read_first_flat_layer_from_file(&exr).unwrap();
    let samples = img
        .layer_data
        .channel_data
        .list
        .iter()
        .find(|c| c.name.to_string() == "samples")
        .map(|c| match &c.sample_data {
            exr::prelude::FlatSamples::F32(v) => v.clone(),
            other => panic!("samples: {other:?}"),
        })
        .expect("a samples channel");
    let (lo, hi) = samples
        .iter()
        .fold((f32::MAX, 0f32), |(l, h), &n| (l.min(n), h.max(n)));
    assert!(lo >= 4.0 && hi <= 256.0 && lo < hi, "{lo}..{hi}");
}

/// Every glTF asset of ../shared/scenes, and the Sibenik OBJ, render with
/// no TOML: the picture has the size the rules give and is not black.
#[test]
fn model_files_render_as_scenes_without_toml() {
    let dir = tmpdir("models");
    for (asset, size) in [
        ("gltf/DamagedHelmet/glTF/DamagedHelmet.gltf", (64, 48)),
        (
            "gltf/AlphaBlendModeTest/glTF/AlphaBlendModeTest.gltf",
            (64, 48),
        ),
        (
            "gltf/TextureTransformTest/glTF/TextureTransformTest.gltf",
            (64, 48),
        ),
        (
            "gltf/TextureSettingsTest/glTF/TextureSettingsTest.gltf",
            (64, 48),
        ),
        (
            "gltf/EmissiveStrengthTest/glTF/EmissiveStrengthTest.gltf",
            (64, 48),
        ),
        ("gltf/SpecularTest/glTF/SpecularTest.gltf", (64, 48)),
        // Its camera's aspectRatio is 1: the height follows --width.
        ("gltf/Cameras/glTF/Cameras.gltf", (64, 64)),
        ("obj/Sibenik_Cathedral/sibenik.obj.gz", (64, 48)),
    ] {
        let model = shared(&format!("scenes/{asset}"));
        let out = dir.join("out.png");
        let mut cmd = tessera();
        cmd.arg("render").arg(&model).arg("-o").arg(&out);
        cmd.args([
            "--width",
            "64",
            "--samples",
            "1",
            "--threads",
            "2",
            "--json",
        ]);
        if size.1 != size.0 {
            cmd.args(["--height", "48"]);
        }
        let (o, stdout, stderr) = run(&mut cmd);
        assert!(o.status.success(), "{asset}: {stderr}");
        // What the frame holds, and what it cost before the first ray.
        let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        let scene = &v["scene"];
        assert!(scene["triangles"].as_u64() > Some(0), "{asset}: {stdout}");
        for key in ["load_seconds", "open_seconds", "prepare_seconds"] {
            assert!(v[key].as_f64() >= Some(0.0), "{asset}: {key} in {stdout}");
        }
        // The trees' build is part of the frame's preparation.
        let tree = v["tree_seconds"].as_f64().unwrap();
        assert!(
            tree > 0.0 && Some(tree) <= v["prepare_seconds"].as_f64(),
            "{asset}: tree_seconds in {stdout}"
        );
        if asset.starts_with("gltf/DamagedHelmet") {
            // 46,356 indices; five 2048x2048 images (colour, metal and
            // roughness, normal, occlusion, emission) of 4 bytes a texel,
            // all held while the process ran.
            assert_eq!(scene["triangles"], 15_452, "{stdout}");
            assert_eq!(scene["textures"], 5, "{stdout}");
            assert_eq!(scene["texture_bytes"], 5 * 2048 * 2048 * 4, "{stdout}");
            assert!(
                v["peak_rss_bytes"].as_u64() > Some(5 * 2048 * 2048 * 4),
                "{stdout}"
            );
        }
        let img = image::open(&out).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), size, "{asset}");
        let lit = img.pixels().filter(|p| p.0.iter().any(|&c| c > 40)).count();
        assert!(lit > 64 * 48 / 20, "{asset}: only {lit} pixels lit");
    }
}

/// Cameras.gltf's perspective camera (node at (0.5, 0.5, 3), yfov 0.7)
/// looks at the unit square tilted 45 degrees about x: the pixels the
/// documented projection puts well inside the square are lit, those well
/// outside are background. Its orthographic camera is refused.
#[test]
fn a_gltf_camera_shows_its_quad_where_the_projection_puts_it() {
    let dir = tmpdir("cameras");
    let model = shared("scenes/gltf/Cameras/glTF/Cameras.gltf");
    let out = dir.join("c.png");
    let (o, _, stderr) = run(tessera()
        .arg("render")
        .arg(&model)
        .arg("-o")
        .arg(&out)
        .args(["--width", "64", "--samples", "1"]));
    assert!(o.status.success(), "{stderr}");
    let img = image::open(&out).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (64, 64));
    // The square's corners, rotated by the node's quaternion (-0.383, 0,
    // 0, 0.92375) about x, projected: x' = x / (depth t) and so on with
    // t = tan(0.35), the camera at (0.5, 0.5, 3) looking down -Z.
    let (s, c) = (
        2.0 * -0.383f64 * 0.92375,
        0.92375f64 * 0.92375 - 0.383 * 0.383,
    );
    let t = 0.35f64.tan();
    let corner = |x: f64, y: f64| {
        let (py, pz) = (y * c, y * s);
        let d = [x - 0.5, py - 0.5, pz - 3.0];
        let depth = -d[2];
        (
            (d[0] / (depth * t) + 1.0) / 2.0 * 64.0,
            (1.0 - d[1] / (depth * t)) / 2.0 * 64.0,
        )
    };
    let poly = [
        corner(0.0, 0.0),
        corner(1.0, 0.0),
        corner(1.0, 1.0),
        corner(0.0, 1.0),
    ];
    // Signed distance (pixels) of a point inside the convex polygon: > 0 inside.
    let inside = |x: f64, y: f64| {
        (0..4)
            .map(|i| {
                let (a, b) = (poly[i], poly[(i + 1) % 4]);
                let (ex, ey) = (b.0 - a.0, b.1 - a.1);
                ((x - a.0) * ey - (y - a.1) * ex) / (ex * ex + ey * ey).sqrt()
            })
            .fold(f64::INFINITY, f64::min)
    };
    let sign = if inside(32.0, 40.0) > 0.0 { 1.0 } else { -1.0 };
    let (mut lit_in, mut dark_out) = (0, 0);
    for y in 0..64u32 {
        for x in 0..64u32 {
            let d = sign * inside(x as f64 + 0.5, y as f64 + 0.5);
            let v = img.get_pixel(x, y).0;
            if d > 1.5 {
                assert!(v[0] > 20, "({x}, {y}) inside the square is dark: {v:?}");
                lit_in += 1;
            } else if d < -1.5 {
                assert_eq!(v, [0, 0, 0], "({x}, {y}) outside the square is lit");
                dark_out += 1;
            }
        }
    }
    assert!(lit_in > 300 && dark_out > 2000, "{lit_in} {dark_out}");
    // The orthographic camera, by index; a camera that is not there.
    let (o, _, stderr) = run(tessera()
        .arg("render")
        .arg(&model)
        .args(["--camera", "1", "-o"])
        .arg(&out));
    assert_eq!(o.status.code(), Some(1));
    assert_eq!(
        stderr,
        format!(
            "error: {}: --camera 1: camera 1 is orthographic, which Tessera's camera model (a pinhole, docs/scene-format.md) cannot render: pick a perspective camera (its cameras: 0 (perspective), 1 (orthographic)) or \"auto\"\n",
            model.display()
        )
    );
    let (o, _, stderr) = run(tessera()
        .arg("render")
        .arg(&model)
        .args(["--camera", "Main", "-o"])
        .arg(&out));
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr.ends_with("--camera Main: no camera named \"Main\" in the file's default scene (its cameras: 0 (perspective), 1 (orthographic))\n"),
        "{stderr}"
    );
}

/// What used to be read as TOML: a .glb renders; a PLY is refused with
/// the TOML to write; `--camera` on a TOML scene is refused.
#[test]
fn glb_renders_ply_is_refused_and_camera_needs_a_model() {
    let dir = tmpdir("glb");
    let out = dir.join("b.png");
    let (o, _, stderr) = run(tessera()
        .arg("render")
        .arg(repo().join("fuzz/seeds/gltf/Box.glb"))
        .arg("-o")
        .arg(&out)
        .args(["--width", "32", "--height", "24", "--samples", "1"]));
    assert!(o.status.success(), "{stderr}");
    let ply = dir.join("m.ply");
    std::fs::write(&ply, "ply\n").unwrap();
    let (o, _, stderr) = run(tessera().arg("render").arg(&ply));
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr.starts_with(&format!(
            "error: {}: a PLY file is a mesh without camera, lights or materials, so it is not a scene by itself: wrap it in a TOML scene",
            ply.display()
        )) && stderr.contains("[[objects]]\ntype = \"mesh\"\npath = \"m.ply\"\ncamera = \"auto\""),
        "{stderr}"
    );
    let scene = dir.join("s.toml");
    std::fs::write(&scene, GOOD).unwrap();
    let (o, _, stderr) = run(tessera().arg("render").arg(&scene).args(["--camera", "0"]));
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr.contains("--camera picks a camera of a model file given as the scene"),
        "{stderr}"
    );
}

/// `--environment FILE` and `[world] environment = "FILE"` light a
/// path-traced scene alike (the same bytes), the image changes the
/// picture, and a missing file, a file that is no image, a scale without
/// an image and a value of the wrong type are refused by name.
#[test]
fn an_environment_image_lights_the_scene_by_key_or_by_flag() {
    let dir = tmpdir("environment");
    support::write_sky_exr(&dir.join("sky.exr"));
    let path_scene = GOOD.replace("samples = 1", "samples = 4\nintegrator = \"path\"");
    std::fs::write(dir.join("plain.toml"), &path_scene).unwrap();
    std::fs::write(
        dir.join("keyed.toml"),
        format!("{path_scene}\n[world]\nenvironment = \"sky.exr\"\n"),
    )
    .unwrap();
    let render = |scene: &str, extra: &[&str], out: &str| {
        let (o, _, stderr) = run(tessera()
            .arg("render")
            .arg(dir.join(scene))
            .arg("-o")
            .arg(dir.join(out))
            .args(["--threads", "2"])
            .args(extra));
        assert!(o.status.success(), "{scene} {extra:?}: {stderr}");
        std::fs::read(dir.join(out)).unwrap()
    };
    let sky = dir.join("sky.exr");
    let keyed = render("keyed.toml", &[], "keyed.png");
    let flagged = render(
        "plain.toml",
        &["--environment", sky.to_str().unwrap()],
        "flagged.png",
    );
    let plain = render("plain.toml", &[], "plain.png");
    assert_eq!(keyed, flagged, "the flag and the key render alike");
    // --json names the image and what it holds: 32 x 16 texels of 12
    // bytes, and 32 x 15 cells of a density and a CDF entry (4 bytes each).
    let (o, stdout, stderr) = run(tessera()
        .arg("render")
        .arg(dir.join("keyed.toml"))
        .arg("-o")
        .arg(dir.join("json.png"))
        .arg("--json"));
    assert!(o.status.success(), "{stderr}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let env = &v["scene"]["environment"];
    assert_eq!(env["name"], "sky.exr", "{stdout}");
    assert_eq!(
        (env["width"].as_u64(), env["height"].as_u64()),
        (Some(32), Some(16))
    );
    assert_eq!(
        env["bytes"].as_u64(),
        Some(32 * 16 * 12 + 32 * 15 * 8),
        "{stdout}"
    );
    assert_ne!(keyed, plain, "the image lights the scene");
    // Under Whitted the image lights nothing, and the render says so.
    let (o, _, stderr) = run(tessera()
        .arg("render")
        .arg(dir.join("keyed.toml"))
        .arg("-o")
        .arg(dir.join("whitted.png"))
        .args(["--integrator", "whitted"]));
    assert!(o.status.success(), "{stderr}");
    assert!(
        stderr.contains(
            "warning: the environment image sky.exr lights the path integrator only; this render is whitted"
        ),
        "{stderr}"
    );

    expect_failure(
        &path_scene,
        &["--environment", "missing.exr"],
        &["--environment", "missing.exr", "cannot read"],
    );
    expect_failure(
        &format!("{path_scene}\n[world]\nenvironment = \"bad.toml\"\n"),
        &[],
        &[
            "world.environment",
            "bad.toml: is not an EXR, HDR, PNG or JPEG image",
        ],
    );
    expect_failure(
        &format!("{path_scene}\n[world]\nenvironment = [0.1, 0.1, 0.1]\nenvironment_scale = 2\n"),
        &[],
        &[
            "world.environment_scale",
            "applies to an environment image only",
        ],
    );
    expect_failure(
        &format!("{path_scene}\n[world]\nenvironment = 5\n"),
        &[],
        &["a colour [r, g, b] or an equirectangular image file's name"],
    );
}
