//! What a bench run prints and writes: the CSV per suite, `--json`, and
//! the summary table.

use crate::cli::outln;

use super::Run;

/// Column names of every suite's CSV (tests/bench_quick.rs checks them).
pub(super) const CSV_HEADER: &str = "suite,scene,backend,device,threads,width,height,samples,sampler,max_depth,precision,wall_s,rays_primary,rays_shadow,rays_reflection,rays_refraction,rays_total,mrays_per_s,pixels_per_s,gpu_s,rmse,psnr_db,rel_mse,flip_mean,image";

pub(super) fn csv_row(r: &Run) -> String {
    let e = r.error;
    let f = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6e}"));
    let mut row = format!(
        "{},{},{},\"{}\",{},{},{},{},{},{},{},{:.6},{},{},{},{},{},{:.3},{:.1},{},{},{},{},{},{}",
        r.suite,
        r.scene,
        r.backend,
        r.device.replace('"', "'"),
        r.threads,
        r.settings.width,
        r.settings.height,
        r.settings.samples,
        r.settings.sampler.name(),
        r.settings.max_depth,
        r.precision.name(),
        r.seconds,
        r.rays.primary,
        r.rays.shadow,
        r.rays.reflection,
        r.rays.refraction,
        r.rays.total(),
        r.mrays_per_s(),
        r.pixels_per_s(),
        f(r.gpu_seconds),
        f(e.map(|e| e.rmse)),
        f(e.map(|e| e.psnr_db)),
        f(e.map(|e| e.rel_mse)),
        f(e.map(|e| e.flip_mean)),
        r.image
    );
    for (_, v) in &r.extra {
        row.push(',');
        row.push_str(v);
    }
    row
}

/// A run as `tessera bench --json` prints it: the CSV's columns under the
/// names `tessera render --json` uses for the same things (docs/cli.md).
pub fn run_json(r: &Run) -> serde_json::Value {
    serde_json::json!({
        "suite": r.suite,
        "scene": r.scene,
        "backend": r.backend.name(),
        "device": r.device,
        "threads": r.threads,
        "width": r.settings.width,
        "height": r.settings.height,
        "samples": r.settings.samples,
        "sampler": r.settings.sampler.name(),
        "max_depth": r.settings.max_depth,
        "precision": r.precision.name(),
        "seconds": r.seconds,
        "gpu_seconds": r.gpu_seconds,
        "rays": {
            "primary": r.rays.primary,
            "shadow": r.rays.shadow,
            "reflection": r.rays.reflection,
            "refraction": r.rays.refraction,
        },
        "rays_per_second": r.rays.total() as f64 / r.seconds,
        "pixels_per_second": r.pixels_per_s(),
        "error": r.error.map(|e| serde_json::json!({
            "rmse": e.rmse,
            "psnr_db": e.psnr_db,
            "rel_mse": e.rel_mse,
            "flip_mean": e.flip_mean,
        })),
        "image": r.image,
        "extra": r.extra.iter().map(|(k, v)| (k.to_string(), serde_json::Value::from(v.as_str()))).collect::<serde_json::Map<_, _>>(),
    })
}

/// The summary table on stdout.
pub fn print_summary(runs: &[Run]) {
    outln!(
        "{:<10} {:<14} {:<4} {:>9} {:>4} {:<8} {:>3} {:<4} {:>9} {:>9} {:>10} {:>9} {:>7}  notes",
        "suite",
        "scene",
        "back",
        "size",
        "spp",
        "sampler",
        "dep",
        "prec",
        "time_s",
        "Mrays/s",
        "RMSE",
        "PSNR_dB",
        "FLIP"
    );
    for r in runs {
        let e = r
            .error
            .map_or(["-".to_string(), "-".to_string(), "-".to_string()], |e| {
                [
                    format!("{:.3e}", e.rmse),
                    format!("{:.2}", e.psnr_db),
                    format!("{:.4}", e.flip_mean),
                ]
            });
        let notes: Vec<String> = r.extra.iter().map(|(k, v)| format!("{k}={v}")).collect();
        outln!(
            "{:<10} {:<14} {:<4} {:>9} {:>4} {:<8} {:>3} {:<4} {:>9.4} {:>9.1} {:>10} {:>9} {:>7}  {}",
            r.suite,
            r.scene,
            r.backend,
            format!("{}x{}", r.settings.width, r.settings.height),
            r.settings.samples,
            r.settings.sampler.name(),
            r.settings.max_depth,
            r.precision.name(),
            r.seconds,
            r.mrays_per_s(),
            e[0],
            e[1],
            e[2],
            notes.join(" ")
        );
    }
}
