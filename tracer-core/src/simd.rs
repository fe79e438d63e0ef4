//! The SIMD instruction sets the CPU paths are built for, chosen at run
//! time (the crate itself is compiled for the baseline of the target, so
//! that every build rounds alike; wider code runs in `#[target_feature]`
//! functions).

/// The instruction sets the SIMD paths are compiled for (the CPU stream
/// renderer, the BVH's packet walk), picked at run time. All give
/// bit-identical results.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SimdLevel {
    /// What every CPU of the target has (SSE2 on x86-64, NEON on aarch64):
    /// 8 lanes in the stream renderer, 4 rays per node test in the packet walk.
    Baseline,
    /// x86-64 AVX2: 8 lanes; 8 rays per node test.
    Avx2,
    /// x86-64 AVX-512F: 16 lanes; 16 rays per node test (ray queries only:
    /// renders use AVX2 for the packet walk, see `bvh::render_level`).
    Avx512,
}

impl SimdLevel {
    /// Every level this CPU can run, baseline first.
    pub fn available() -> Vec<SimdLevel> {
        [SimdLevel::Baseline, SimdLevel::Avx2, SimdLevel::Avx512]
            .into_iter()
            .filter(|l| l.is_available())
            .collect()
    }

    /// Whether this CPU can run the level (no allocation: for hot paths).
    #[inline]
    pub fn is_available(self) -> bool {
        match self {
            SimdLevel::Baseline => true,
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx2 => std::arch::is_x86_feature_detected!("avx2"),
            #[cfg(target_arch = "x86_64")]
            SimdLevel::Avx512 => std::arch::is_x86_feature_detected!("avx512f"),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The best level this CPU can run.
    pub fn detect() -> SimdLevel {
        *Self::available().last().unwrap_or(&SimdLevel::Baseline)
    }
}

impl SimdLevel {
    pub fn name(self) -> &'static str {
        match self {
            SimdLevel::Baseline => "baseline",
            SimdLevel::Avx2 => "avx2",
            SimdLevel::Avx512 => "avx512",
        }
    }
}

impl std::str::FromStr for SimdLevel {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "baseline" => Ok(SimdLevel::Baseline),
            "avx2" => Ok(SimdLevel::Avx2),
            "avx512" => Ok(SimdLevel::Avx512),
            _ => Err(format!(
                "unknown SIMD level {s:?}: expected \"baseline\", \"avx2\" or \"avx512\""
            )),
        }
    }
}

/// The SIMD level of the CPU paths, chosen once: the best this CPU
/// has, or a lower one named by `TESSERA_CPU_SIMD` (`baseline`, `avx2`,
/// `avx512`), for benchmarks; results are the same bits at every level.
pub fn level() -> SimdLevel {
    static LEVEL: std::sync::OnceLock<SimdLevel> = std::sync::OnceLock::new();
    *LEVEL.get_or_init(|| {
        let best = SimdLevel::detect();
        match std::env::var("TESSERA_CPU_SIMD")
            .ok()
            .and_then(|v| v.parse::<SimdLevel>().ok())
        {
            Some(l) if l.is_available() => l,
            _ => best,
        }
    })
}
