//! The settings of adaptive sampling (issue 17): the keys of a scene's
//! `[render]` table and of the command line ([`AdaptiveSpec`]), resolved
//! into [`AdaptiveSettings`]. What a render does with them is
//! [`crate::adaptive`] (blocks, masks, statistics) and
//! `render::adaptive` (the rounds).

use super::{MAX_SAMPLES, RenderSettings};
use crate::film::SampleRange;
use crate::sampling::Sampler;

/// Defaults of `--min-samples` and `--max-samples`.
pub const DEFAULT_MIN_SAMPLES: u32 = 16;
pub const DEFAULT_MAX_SAMPLES: u32 = 1024;

/// What an adaptive render's target bounds.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum AdaptiveMode {
    /// Every pixel's standard error (issue 17): the meaning of
    /// `target_error` and `relative_error` per pixel.
    #[default]
    Pixel,
    /// The image's estimated RMSE (issue 36): `target_error` an RMSE,
    /// `relative_error` a share of the image's mean, each 8x8 block's
    /// samples in proportion to its noise over the square root of its cost
    /// (`crate::adaptive::optimal`).
    Image,
}

impl AdaptiveMode {
    pub fn name(self) -> &'static str {
        match self {
            AdaptiveMode::Pixel => "pixel",
            AdaptiveMode::Image => "image",
        }
    }
}

impl std::str::FromStr for AdaptiveMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "pixel" => Ok(AdaptiveMode::Pixel),
            "image" => Ok(AdaptiveMode::Image),
            _ => Err(format!("unknown adaptive mode {s:?} (pixel or image)")),
        }
    }
}

/// The error target and the sample bounds of an adaptive render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptiveSettings {
    /// Largest standard error of a pixel's mean, per linear RGB channel
    /// (0: no absolute target).
    pub target_error: f64,
    /// Largest standard error as a share of the mean of the pixel's
    /// brightest channel, e.g. 0.02 (0: no relative target).
    pub relative_error: f64,
    pub min_samples: u32,
    pub max_samples: u32,
    /// What the targets bound: each pixel's error or the image's.
    pub mode: AdaptiveMode,
}

/// When a pixel is converged: its standard error in every channel is at
/// most `max(absolute, relative * m)`, `m` the largest of its three
/// channel means. An absolute target alone is exposure-dependent (the
/// same noise is invisible on a bright wall and plain in a shadow); a
/// relative one alone would sample dark noisy pixels to the maximum, so
/// the absolute target, when given, is its floor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Target {
    pub absolute: f64,
    pub relative: f64,
}

impl Target {
    /// The largest variance of the mean allowed for a pixel whose
    /// brightest channel mean is `mean`.
    pub fn limit_sq(&self, mean: f64) -> f64 {
        let l = self.absolute.max(self.relative * mean);
        l * l
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AdaptiveError {
    #[error("target_error must be a finite number above 0, got {0}")]
    TargetError(f64),
    #[error("relative_error must be a finite number above 0, got {0}")]
    RelativeError(f64),
    #[error(
        "min_samples must be at least 2 (the error estimate needs two samples of a pixel), got {0}"
    )]
    MinTooSmall(u32),
    #[error("max_samples must be at most {MAX_SAMPLES}, got {0}")]
    MaxTooLarge(u32),
    #[error("min_samples ({min}) must not exceed max_samples ({max})")]
    MinAboveMax { min: u32, max: u32 },
}

impl AdaptiveSettings {
    pub fn validate(&self) -> Result<(), AdaptiveError> {
        // Each target is off (0) or a finite number above 0, and one is on.
        let ok = |v: f64| v >= 0.0 && v.is_finite();
        if !ok(self.target_error) || (self.target_error == 0.0 && self.relative_error == 0.0) {
            return Err(AdaptiveError::TargetError(self.target_error));
        }
        if !ok(self.relative_error) {
            return Err(AdaptiveError::RelativeError(self.relative_error));
        }
        if self.min_samples < 2 {
            return Err(AdaptiveError::MinTooSmall(self.min_samples));
        }
        if self.max_samples > MAX_SAMPLES {
            return Err(AdaptiveError::MaxTooLarge(self.max_samples));
        }
        if self.min_samples > self.max_samples {
            return Err(AdaptiveError::MinAboveMax {
                min: self.min_samples,
                max: self.max_samples,
            });
        }
        Ok(())
    }

    /// The target in words: "target error E", "relative error R", or both
    /// ("image RMSE E", "relative image RMSE R" in the image mode).
    pub fn describe_target(&self) -> String {
        let (abs, rel) = match self.mode {
            AdaptiveMode::Pixel => ("target error", "relative error"),
            AdaptiveMode::Image => ("image RMSE", "relative image RMSE"),
        };
        let abs = (self.target_error > 0.0).then(|| format!("{abs} {}", self.target_error));
        let rel = (self.relative_error > 0.0).then(|| format!("{rel} {}", self.relative_error));
        [abs, rel]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>()
            .join(", ")
    }

    pub fn target(&self) -> Target {
        Target {
            absolute: self.target_error,
            relative: self.relative_error,
        }
    }

    /// The sample range of each round: `0..min`, then doubling up to
    /// `max`. In the image mode each block has its own range from round 1
    /// on; the rounds are then `0..min` and as many more as the mode may
    /// take ([`crate::adaptive::optimal::RmseSettings::max_rounds`]), each
    /// nominally `min` samples a pixel (what the farm's lease sizing
    /// expects of it before it is decided).
    pub fn rounds(&self) -> Vec<SampleRange> {
        if self.mode == AdaptiveMode::Image {
            let min = self.min_samples;
            let rounds = crate::adaptive::optimal::RmseSettings::from(self).max_rounds();
            let mut out = vec![SampleRange::new(0, min)];
            out.resize(
                rounds as usize,
                SampleRange::new(min, min.saturating_mul(2)),
            );
            return out;
        }
        let mut out = vec![SampleRange::new(0, self.min_samples)];
        let mut end = self.min_samples;
        while end < self.max_samples {
            let next = end.saturating_mul(2).min(self.max_samples);
            out.push(SampleRange::new(end, next));
            end = next;
        }
        out
    }

    /// The settings an adaptive render traces with: `samples` is the most a
    /// pixel can get, and samples are placed progressively (sample k is the
    /// same whatever the count).
    pub fn render_settings(&self, base: RenderSettings) -> RenderSettings {
        RenderSettings {
            samples: self.max_samples,
            sampler: Sampler::Progressive,
            ..base
        }
    }
}

/// The adaptive keys as given (scene file or command line), before defaults.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AdaptiveSpec {
    pub target_error: Option<f64>,
    pub relative_error: Option<f64>,
    pub min_samples: Option<u32>,
    pub max_samples: Option<u32>,
    pub mode: Option<AdaptiveMode>,
}

impl AdaptiveSpec {
    /// Checks each given value on its own terms (and min against max when
    /// both are given); `Err` names the key and what is wrong with it.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        let full = AdaptiveSettings {
            target_error: self.target_error.unwrap_or(1.0),
            relative_error: self.relative_error.unwrap_or(0.0),
            min_samples: self.min_samples.unwrap_or(2),
            max_samples: self.max_samples.unwrap_or(MAX_SAMPLES),
            mode: AdaptiveMode::Pixel,
        };
        check_given_relative(self.relative_error)
            .and_then(|()| full.validate())
            .map_err(|e| {
                let key = match e {
                    AdaptiveError::TargetError(_) => "target_error",
                    AdaptiveError::RelativeError(_) => "relative_error",
                    AdaptiveError::MinTooSmall(_) | AdaptiveError::MinAboveMax { .. } => {
                        "min_samples"
                    }
                    _ => "max_samples",
                };
                let m = e.to_string();
                let what = m.split_once(' ').map_or(m.clone(), |(_, w)| w.to_string());
                (key, what)
            })
    }

    /// `over` (the command line) over `self` (the scene file), defaults
    /// for what neither gives. `None` without a target error, absolute or
    /// relative (a uniform render); then giving sample bounds on the
    /// command line is an error.
    pub fn resolve(&self, over: &AdaptiveSpec) -> Result<Option<AdaptiveSettings>, String> {
        let target_error = over.target_error.or(self.target_error);
        let relative_error = over.relative_error.or(self.relative_error);
        check_given_relative(relative_error).map_err(|e| e.to_string())?;
        let mode = over.mode.or(self.mode);
        if target_error.is_none() && relative_error.is_none() {
            // As the sample bounds: the file's mode waits for a target
            // from the command line; the command line's needs one.
            if over.mode == Some(AdaptiveMode::Image) {
                return Err(
                    "--adaptive-mode image needs a target: \
                            give --target-error (an RMSE) or --relative-error (or [render] target_error or relative_error)"
                        .into(),
                );
            }
            if over.min_samples.is_some() || over.max_samples.is_some() {
                return Err(
                    "--min-samples and --max-samples apply to adaptive sampling: \
                            give --target-error or --relative-error (or [render] target_error or relative_error) too"
                        .into(),
                );
            }
            return Ok(None);
        }
        let min_samples = over
            .min_samples
            .or(self.min_samples)
            .unwrap_or(DEFAULT_MIN_SAMPLES);
        let a = AdaptiveSettings {
            target_error: target_error.unwrap_or(0.0),
            relative_error: relative_error.unwrap_or(0.0),
            min_samples,
            max_samples: over
                .max_samples
                .or(self.max_samples)
                .unwrap_or(DEFAULT_MAX_SAMPLES.max(min_samples)),
            mode: mode.unwrap_or_default(),
        };
        a.validate().map_err(|e| e.to_string())?;
        Ok(Some(a))
    }
}

/// A relative target, when given, must be on: in the settings 0 means
/// "none", but nobody asks for none by giving 0.
fn check_given_relative(r: Option<f64>) -> Result<(), AdaptiveError> {
    match r {
        Some(r) if !(r > 0.0 && r.is_finite()) => Err(AdaptiveError::RelativeError(r)),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(min: u32, max: u32) -> AdaptiveSettings {
        AdaptiveSettings {
            target_error: 0.01,
            relative_error: 0.0,
            min_samples: min,
            max_samples: max,
            mode: AdaptiveMode::Pixel,
        }
    }

    #[test]
    fn rounds_double_up_to_max() {
        let r = |min, max| {
            settings(min, max)
                .rounds()
                .iter()
                .map(|r| (r.start, r.end))
                .collect::<Vec<_>>()
        };
        assert_eq!(r(16, 128), vec![(0, 16), (16, 32), (32, 64), (64, 128)]);
        assert_eq!(r(4, 4), vec![(0, 4)]);
        assert_eq!(r(3, 20), vec![(0, 3), (3, 6), (6, 12), (12, 20)]);
    }

    #[test]
    fn bad_settings_are_named() {
        let mut s = settings(16, 1024);
        s.target_error = 0.0;
        assert_eq!(s.validate(), Err(AdaptiveError::TargetError(0.0)));
        s.target_error = f64::NAN;
        assert!(matches!(s.validate(), Err(AdaptiveError::TargetError(_))));
        assert_eq!(
            settings(1, 4).validate(),
            Err(AdaptiveError::MinTooSmall(1))
        );
        assert_eq!(
            settings(64, 32).validate(),
            Err(AdaptiveError::MinAboveMax { min: 64, max: 32 })
        );
        assert_eq!(
            settings(2, 70_000).validate(),
            Err(AdaptiveError::MaxTooLarge(70_000))
        );
        let e = settings(64, 32).validate().unwrap_err().to_string();
        assert_eq!(e, "min_samples (64) must not exceed max_samples (32)");
    }
}
