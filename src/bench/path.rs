//! The `path` suite (run only when named: it needs Mitsuba 3): Tessera's
//! path integrator against Mitsuba 3's `path` integrator on one Cornell
//! box, written for both from one description ([`CORNELL`]): RMSE against
//! a converged Tessera f64 reference against render time, for Tessera on
//! each `--backend` and for Mitsuba (variant `$TESSERA_MITSUBA_VARIANT`,
//! default `scalar_rgb`; `python3` with the `mitsuba` package), and the
//! headline: how long Tessera takes to reach the RMSE Mitsuba reaches at
//! its largest sample count (log-log interpolation between Tessera's
//! runs), against Mitsuba's time.
//!
//! The box: five Lambert planes (Mitsuba: squares of side 200), two
//! Lambert spheres and a small emissive quad under the ceiling (two
//! triangles of an OBJ file with `[bsdf] emission` for Tessera, which
//! samples them as lights; a one-sided `rectangle` area emitter for
//! Mitsuba) and a box filter of one pixel. Tessera's sampler is
//! `jittered`: at a square sample count the pixel position and each path
//! vertex's light point and BSDF direction are stratified
//! (`sampling::uniform_pair`); Mitsuba's is `$TESSERA_MITSUBA_SAMPLER`,
//! default `independent` (its default; `stratified`, `multijitter` and
//! `ldsampler` are its stratified ones).

use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use tracer_core::render::{Backend, Precision};
use tracer_core::sampling::Sampler;
use tracer_core::scene::{Integrator, RenderSettings, SceneDesc};

use super::plot::{LinePlot, Series};
use super::{Bench, Run, compare};

type V = [f64; 3];

/// Planes { p : p.n = d } (n facing the camera) and their Lambert colour.
const PLANES: [(V, f64, V); 5] = [
    ([0.0, 1.0, 0.0], 0.0, [0.72, 0.72, 0.72]),
    ([0.0, -1.0, 0.0], -2.0, [0.72, 0.72, 0.72]),
    ([0.0, 0.0, -1.0], -1.0, [0.72, 0.72, 0.72]),
    ([1.0, 0.0, 0.0], -1.0, [0.63, 0.07, 0.05]),
    ([-1.0, 0.0, 0.0], -1.0, [0.12, 0.45, 0.09]),
];
/// Spheres (centre, radius, Lambert colour).
const SPHERES: [(V, f64, V); 2] = [
    ([-0.4, 0.35, 0.3], 0.35, [0.8, 0.8, 0.8]),
    ([0.45, 0.3, -0.3], 0.3, [0.75, 0.7, 0.5]),
];
/// The lamp: corner, edges (emitting on the edge_u x edge_v side, -y) and radiance.
const LAMP: (V, V, V, V) = (
    [-0.25, 1.99, -0.25],
    [0.5, 0.0, 0.0],
    [0.0, 0.0, 0.5],
    [17.0, 12.0, 4.0],
);
/// Half the side of Mitsuba's squares for Tessera's planes: the box is
/// an open corridor of 2 x 2, and a path of at most MAX_DEPTH segments
/// seldom strays 100 units down it. Not larger: with squares of side 2e4
/// Mitsuba's cuda_ad_rgb rendered the box 5% darker than its scalar_rgb
/// (which matched Tessera's mean to 0.1%) on the H200, 2026-12-05.
const PLANE_HALF_SIDE: f64 = 100.0;
const EYE: V = [0.0, 1.0, -3.4];
const LOOK_AT: V = [0.0, 1.0, 0.0];
const FOV_Y: f64 = 40.0;
const MAX_DEPTH: u32 = 8;
/// The suite's one scene, by name.
const CORNELL: &str = "cornell";

fn rgb(v: V) -> String {
    format!("[{}, {}, {}]", v[0], v[1], v[2])
}

fn mi_rgb(v: V) -> String {
    format!("{{'type': 'rgb', 'value': {}}}", rgb(v))
}

/// Tessera's scene (beside `lamp.obj` in its folder).
fn tessera_toml(size: (u32, u32)) -> String {
    let mut s = format!(
        "[render]\nwidth = {}\nheight = {}\nsamples = 1\nmax_depth = {MAX_DEPTH}\n\
         sampler = \"jittered\"\nintegrator = \"path\"\n\n\
         [camera]\nposition = {}\nlook_at = {}\nfov_y = {FOV_Y}\n\n\
         [materials.lamp]\n[bsdf.lamp]\nbase_colour = [0, 0, 0]\nmetallic = 0\nspecular = 0\nemission = {}\n\n\
         [[objects]]\ntype = \"mesh\"\npath = \"lamp.obj\"\nmaterial = \"lamp\"\n\n",
        size.0,
        size.1,
        rgb(EYE),
        rgb(LOOK_AT),
        rgb(LAMP.3)
    );
    let lambert = |s: &mut String, name: String, c: V| {
        let _ = writeln!(
            s,
            "[materials.{name}]\n[bsdf.{name}]\nbase_colour = {}\nmetallic = 0\nspecular = 0\n",
            rgb(c)
        );
    };
    for (i, (n, d, c)) in PLANES.iter().enumerate() {
        lambert(&mut s, format!("plane{i}"), *c);
        let _ = writeln!(
            s,
            "[[objects]]\ntype = \"plane\"\nnormal = {}\ndistance = {d}\nmaterial = \"plane{i}\"\n",
            rgb(*n)
        );
    }
    for (i, (c, r, col)) in SPHERES.iter().enumerate() {
        lambert(&mut s, format!("sphere{i}"), *col);
        let _ = writeln!(
            s,
            "[[objects]]\ntype = \"sphere\"\ncenter = {}\nradius = {r}\nmaterial = \"sphere{i}\"\n",
            rgb(*c)
        );
    }
    s
}

/// The lamp's two triangles, counter-clockwise seen from below.
fn lamp_obj() -> String {
    let (c, u, v, _) = LAMP;
    let p = |a: f64, b: f64| -> V { std::array::from_fn(|k| c[k] + a * u[k] + b * v[k]) };
    let mut s = String::new();
    for q in [p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)] {
        let _ = writeln!(s, "v {} {} {}", q[0], q[1], q[2]);
    }
    s + "f 1 2 3\nf 1 3 4\n"
}

/// Mitsuba's scene dict (Python), `T` being `mi.ScalarTransform4f`.
fn mitsuba_dict(size: (u32, u32), sampler: &str) -> String {
    let mut s = format!(
        "{{'type': 'scene', 'integrator': {{'type': 'path', 'max_depth': {MAX_DEPTH}}},\n\
         'sensor': {{'type': 'perspective', 'fov': {FOV_Y}, 'fov_axis': 'y',\n\
           'to_world': T().look_at(origin={}, target={}, up=[0, 1, 0]),\n\
           'film': {{'type': 'hdrfilm', 'width': {}, 'height': {}, 'pixel_format': 'rgb', 'rfilter': {{'type': 'box'}}}},\n\
           'sampler': {{'type': '{sampler}', 'sample_count': 1}}}},\n",
        rgb(EYE),
        rgb(LOOK_AT),
        size.0,
        size.1
    );
    let diffuse = |c: V| format!("{{'type': 'diffuse', 'reflectance': {}}}", mi_rgb(c));
    for (i, (n, d, c)) in PLANES.iter().enumerate() {
        let o = n.map(|x| x * d);
        let t: V = std::array::from_fn(|k| o[k] + n[k]);
        let up = if n[1].abs() > 0.9 {
            [0.0, 0.0, 1.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let _ = writeln!(
            s,
            "'plane{i}': {{'type': 'rectangle', 'to_world': T().look_at(origin={}, target={}, up={}) @ T().scale([{PLANE_HALF_SIDE}, {PLANE_HALF_SIDE}, 1]), 'bsdf': {}}},",
            rgb(o),
            rgb(t),
            rgb(up),
            diffuse(*c)
        );
    }
    for (i, (c, r, col)) in SPHERES.iter().enumerate() {
        let _ = writeln!(
            s,
            "'sphere{i}': {{'type': 'sphere', 'center': {}, 'radius': {r}, 'bsdf': {}}},",
            rgb(*c),
            diffuse(*col)
        );
    }
    // Mitsuba's square [-1, 1]^2 (normal +z) onto the lamp (normal eu x ev).
    let (c, u, v, l) = LAMP;
    let n = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    let rows: Vec<String> = (0..3)
        .map(|k| {
            format!(
                "[{}, {}, {}, {}]",
                0.5 * u[k],
                0.5 * v[k],
                n[k] / len,
                c[k] + 0.5 * (u[k] + v[k])
            )
        })
        .collect();
    let _ = writeln!(
        s,
        "'lamp': {{'type': 'rectangle', 'to_world': T([{}, [0, 0, 0, 1]]), 'bsdf': {}, 'emitter': {{'type': 'area', 'radiance': {}}}}},",
        rows.join(", "),
        diffuse([0.0; 3]),
        mi_rgb(l)
    );
    s.push('}');
    s
}

/// Mitsuba's renders at each of `counts` samples per pixel (seed 1), each
/// timed alone after a 1-spp warm-up (scene loading left out; the LLVM
/// and CUDA variants also render each count once untimed first, leaving
/// their kernels' compilation out) up to its image evaluated and the
/// device synchronised (the JIT variants evaluate lazily), not its copy
/// out: (seconds, linear RGB image).
fn mitsuba_runs(
    dir: &Path,
    variant: &str,
    sampler: &str,
    size: (u32, u32),
    counts: &[u32],
) -> Result<Vec<(f64, Vec<[f32; 3]>)>> {
    let script = format!(
        "import json, struct, sys, time\n\
         import drjit as dr\n\
         import mitsuba as mi\n\
         mi.set_variant({variant:?})\n\
         T = mi.ScalarTransform4f\n\
         scene = mi.load_dict({dict})\n\
         mi.render(scene, spp=1)\n\
         times = []\n\
         for spp in {counts:?}:\n\
         \x20   if not {variant:?}.startswith('scalar'):\n\
         \x20       dr.eval(mi.render(scene, spp=spp, seed=0))\n\
         \x20       dr.sync_thread()\n\
         \x20   t = time.perf_counter()\n\
         \x20   img = mi.render(scene, spp=spp, seed=1)\n\
         \x20   dr.eval(img)\n\
         \x20   dr.sync_thread()\n\
         \x20   times.append(time.perf_counter() - t)\n\
         \x20   a = [float(x) for x in mi.TensorXf(img).array]\n\
         \x20   open(sys.argv[1] + '/mitsuba-%d.f32' % spp, 'wb').write(struct.pack('<%df' % len(a), *a))\n\
         print(json.dumps({{'times': times, 'version': mi.__version__}}))\n",
        dict = mitsuba_dict(size, sampler),
    );
    let out = std::process::Command::new("python3")
        .arg("-c")
        .arg(&script)
        .arg(dir)
        .output()
        .context("cannot run python3 (the path suite's Mitsuba 3 runs need it)")?;
    if !out.status.success() {
        bail!(
            "Mitsuba 3 (variant {variant}) failed; the path suite needs python3 -m pip install mitsuba:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let report: serde_json::Value = serde_json::from_slice(&out.stdout)
        .with_context(|| format!("Mitsuba's report: {}", String::from_utf8_lossy(&out.stdout)))?;
    let times = report["times"]
        .as_array()
        .context("Mitsuba's report has no times")?;
    let mut runs = Vec::new();
    for (&spp, t) in counts.iter().zip(times) {
        let file = dir.join(format!("mitsuba-{spp}.f32"));
        let bytes =
            std::fs::read(&file).with_context(|| format!("cannot read {}", file.display()))?;
        let f: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if f.len() != (size.0 * size.1 * 3) as usize {
            bail!(
                "{}: {} values, not {}x{}x3",
                file.display(),
                f.len(),
                size.0,
                size.1
            );
        }
        runs.push((
            t.as_f64().context("a time")?,
            f.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        ));
    }
    Ok(runs)
}

/// The time to reach RMSE `target` along `points` (seconds, RMSE) sorted
/// by time: log-log interpolation between the runs around it; `None`
/// where no run reaches it.
fn time_to_reach(points: &[(f64, f64)], target: f64) -> Option<f64> {
    if let Some(&(t, e)) = points.first()
        && e <= target
    {
        return Some(t);
    }
    points.windows(2).find_map(|w| {
        let ((t0, e0), (t1, e1)) = (w[0], w[1]);
        (e1 <= target && e0 > target).then(|| {
            let f = (target.ln() - e0.ln()) / (e1.ln() - e0.ln());
            (t0.ln() + f * (t1.ln() - t0.ln())).exp()
        })
    })
}

impl Bench {
    /// Tessera against Mitsuba 3 on the Cornell box: RMSE against time.
    pub(super) fn suite_path(&self) -> Result<Vec<Run>> {
        let size = self.cfg.path_size;
        let mut counts = self.cfg.path_samples.clone();
        counts.sort_unstable();
        counts.dedup();
        let counts = &counts[..];
        let ref_samples = self.cfg.path_reference;
        let variant =
            std::env::var("TESSERA_MITSUBA_VARIANT").unwrap_or_else(|_| "scalar_rgb".into());
        let dir = self.cfg.out.join("path");
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let scene_path = dir.join("cornell.toml");
        std::fs::write(dir.join("lamp.obj"), lamp_obj())?;
        std::fs::write(&scene_path, tessera_toml(size))?;
        let desc = SceneDesc::load(&scene_path)?;
        let base = RenderSettings {
            sampler: Sampler::Jittered,
            integrator: Integrator::Path,
            ..desc.render
        };
        eprintln!("bench: path: Tessera f64 reference at {ref_samples} spp");
        let reference = self.refs.get(&scene_path, &desc, &base, ref_samples)?;
        let mut runs = Vec::new();
        let renderer = |name: &str| vec![("renderer", name.to_string())];
        for &samples in counts {
            let s = RenderSettings { samples, ..base };
            for &b in &self.cfg.backends {
                let mut run = self.measure(
                    "path",
                    CORNELL,
                    b,
                    &desc,
                    &s,
                    Precision::F32,
                    Some(&reference),
                )?;
                run.extra = renderer("tessera");
                runs.push(run);
            }
        }
        let start = Instant::now();
        let sampler =
            std::env::var("TESSERA_MITSUBA_SAMPLER").unwrap_or_else(|_| "independent".into());
        // It goes into the Python script's dict literal.
        if sampler.is_empty() || !sampler.bytes().all(|b| b.is_ascii_lowercase() || b == b'_') {
            bail!(
                "TESSERA_MITSUBA_SAMPLER {sampler:?} is no Mitsuba sampler name (lowercase letters and _)"
            );
        }
        let mitsuba = mitsuba_runs(&dir, &variant, &sampler, size, counts)?;
        let variant = if sampler == "independent" {
            variant
        } else {
            format!("{variant}-{sampler}")
        };
        eprintln!(
            "bench: path: Mitsuba 3 ({variant}) took {:.1} s in all",
            start.elapsed().as_secs_f64()
        );
        for (&samples, (seconds, image)) in counts.iter().zip(mitsuba) {
            let error = compare(&image, &reference, size.0, size.1);
            eprintln!(
                "  path       {CORNELL:<14} mitsuba {variant} {samples:>4} spp {seconds:>8.3} s  RMSE {:.2e}",
                error.rmse
            );
            runs.push(Run {
                suite: "path",
                scene: CORNELL.into(),
                backend: Backend::Cpu,
                device: if variant.starts_with("cuda") {
                    format!("Mitsuba 3 {variant} (CUDA GPU)")
                } else {
                    format!("Mitsuba 3 {variant} on {}", self.cpu_name)
                },
                threads: 0,
                settings: RenderSettings { samples, ..base },
                precision: Precision::F32,
                seconds,
                gpu_seconds: None,
                rays: Default::default(),
                error: Some(error),
                image: String::new(),
                extra: renderer(&format!("mitsuba-{variant}")),
            });
        }
        // Error against time, per renderer and backend.
        let mut series: Vec<Series> = Vec::new();
        for r in &runs {
            let name = format!("{} {}", r.extra[0].1, r.backend.name());
            let point = (r.seconds, r.error.map_or(f64::NAN, |e| e.rmse));
            match series.iter_mut().find(|s| s.name == name) {
                Some(s) => s.points.push(point),
                None => series.push(Series {
                    name,
                    points: vec![point],
                }),
            }
        }
        // The headline: Mitsuba's RMSE at its most samples, and how long
        // each Tessera backend takes to reach it.
        if let Some(m) = series.iter().find(|s| s.name.starts_with("mitsuba"))
            && let Some(&(t_m, e_m)) = m.points.last()
        {
            for s in series.iter().filter(|s| s.name.starts_with("tessera")) {
                let mut pts = s.points.clone();
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                match time_to_reach(&pts, e_m) {
                    Some(t) => eprintln!(
                        "bench: path: {} reaches Mitsuba's RMSE {e_m:.3e} ({t_m:.3} s) in {t:.3} s: {:.2}x Mitsuba's speed",
                        s.name,
                        t_m / t
                    ),
                    None => eprintln!(
                        "bench: path: {} does not reach Mitsuba's RMSE {e_m:.3e} ({t_m:.3} s) within its runs",
                        s.name
                    ),
                }
            }
        }
        LinePlot {
            title: format!(
                "Cornell box, {}x{}: RMSE against a Tessera f64 reference ({ref_samples} spp) against time",
                size.0, size.1
            ),
            x_label: "time per frame (s)".into(),
            y_label: "RMSE".into(),
            log_x: true,
            log_y: true,
            series,
        }
        .write(&dir.join("error_vs_time"))?;
        Ok(runs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_to_reach_interpolates_in_log_log() {
        let pts = [(1.0, 0.1), (4.0, 0.05), (16.0, 0.025)];
        assert_eq!(time_to_reach(&pts, 0.2), Some(1.0));
        let t = time_to_reach(&pts, 0.05 / 2f64.sqrt()).unwrap();
        assert!((t - 8.0).abs() < 1e-9, "{t}");
        assert_eq!(time_to_reach(&pts, 0.01), None);
    }

    #[test]
    fn the_tessera_scene_parses() {
        let dir = std::env::temp_dir().join(format!("tessera-bench-path-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("lamp.obj"), lamp_obj()).unwrap();
        let p = dir.join("cornell.toml");
        std::fs::write(&p, tessera_toml((8, 8))).unwrap();
        let desc = SceneDesc::load(&p).unwrap();
        assert_eq!(desc.render.integrator, Integrator::Path);
        assert_eq!(desc.objects.len(), PLANES.len() + SPHERES.len() + 1);
        std::fs::remove_dir_all(&dir).ok();
    }
}
