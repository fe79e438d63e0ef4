//! `tessera bench --quick`: the CI smoke test of the benchmark command. It
//! checks that every suite's files exist and parse, not the speed.

use std::path::Path;
use std::process::Command;

const SUITES: &[&str] = &["resolution", "samples", "complexity", "depth", "precision"];

fn split_csv(line: &str) -> Vec<String> {
    let mut out = vec![String::new()];
    let mut quoted = false;
    for ch in line.chars() {
        match ch {
            '"' => quoted = !quoted,
            ',' if !quoted => out.push(String::new()),
            c => out.last_mut().unwrap().push(c),
        }
    }
    out
}

#[test]
fn quick_bench_writes_parseable_csv_images_and_plots() {
    let dir = std::env::temp_dir().join(format!("tessera-bench-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = Command::new(env!("CARGO_BIN_EXE_tessera"))
        .args(["bench", "--quick", "--out"])
        .arg(dir.join("out"))
        .arg("--cache")
        .arg(dir.join("cache"))
        .arg("--examples")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("examples"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "bench failed:\n{}\n{}", stdout, String::from_utf8_lossy(&out.stderr));
    assert!(stdout.starts_with("suite      scene"), "summary table missing:\n{stdout}");

    for suite in SUITES {
        let csv = std::fs::read_to_string(dir.join(format!("out/{suite}.csv"))).unwrap();
        let mut lines = csv.lines();
        let header = split_csv(lines.next().unwrap());
        let col = |name: &str| header.iter().position(|h| h == name).unwrap_or_else(|| panic!("{suite}.csv lacks column {name}"));
        let (wall, rays, rmse, psnr, flip, image, backend) =
            (col("wall_s"), col("rays_total"), col("rmse"), col("psnr_db"), col("flip_mean"), col("image"), col("backend"));
        let mut rows = 0;
        for line in lines {
            let f = split_csv(line);
            assert_eq!(f.len(), header.len(), "{suite}.csv: {line}");
            assert!(f[wall].parse::<f64>().unwrap() > 0.0);
            assert!(f[rays].parse::<u64>().unwrap() > 0);
            let e: f64 = f[rmse].parse().unwrap();
            assert!((0.0..1.0).contains(&e), "{suite}: rmse {e}");
            let p: f64 = f[psnr].parse().unwrap();
            assert!(p > 10.0, "{suite}: psnr {p}");
            let fl: f64 = f[flip].parse().unwrap();
            assert!((0.0..1.0).contains(&fl), "{suite}: flip {fl}");
            assert_eq!(f[backend], "cpu");
            let img = image::open(dir.join("out").join(&f[image])).unwrap();
            assert!(img.width() > 0);
            rows += 1;
        }
        assert!(rows >= 2, "{suite}.csv has {rows} rows");
    }
    // The headline plot and the others, as PNG and SVG.
    for plot in ["samples/error_vs_time", "resolution/time_vs_pixels", "complexity/rays_vs_spheres", "depth/time_vs_depth", "depth/error_vs_depth"] {
        let png = image::open(dir.join("out").join(format!("{plot}.png"))).unwrap();
        assert_eq!((png.width(), png.height()), (900, 600));
        let svg = std::fs::read_to_string(dir.join("out").join(format!("{plot}.svg"))).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("</svg>"), "{plot}.svg");
    }
    // More samples must not make the error worse on the grid sampler (1 -> 9 spp).
    let csv = std::fs::read_to_string(dir.join("out/samples.csv")).unwrap();
    let grid: Vec<f64> = csv.lines().skip(1).map(split_csv).filter(|f| f[8] == "grid").map(|f| f[19].parse().unwrap()).collect();
    assert!(grid.first() > grid.last(), "grid error does not fall with samples: {grid:?}");
    let _ = std::fs::remove_dir_all(&dir);
}
