//! Overrides of a scene's `[render]` table: the one shape of "these
//! settings instead of the scene's", whoever gives them.
//!
//! It lives here, beside [`RenderSettings`], because every process that
//! renders or accepts a render needs it and tracer-core is the crate they
//! all share: `tessera render` and `tessera submit` build it from their
//! flags (`src/cli/render.rs` `OverrideArgs`), `tessera-proto` converts the
//! wire's `RenderOverrides` message to and from it (`proto/src/convert.rs`),
//! the coordinator applies it to a submitted scene (`farm/jobs.rs`), and
//! the scene parser applies the file's own `[render]` table to the
//! defaults with it. Overrides are *validated once*, in [`RenderOverrides::apply`]
//! (and [`RenderOverrides::resolve`], which adds adaptive sampling): the
//! settings they give are then valid wherever they travel.

use super::adaptive::{AdaptiveSettings, AdaptiveSpec};
use crate::sampling::Sampler;

use super::{RenderSettings, SceneDesc};

/// Settings that replace a scene's `[render]` values; `None` keeps the
/// scene's.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderOverrides {
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub samples: Option<u32>,
    pub max_depth: Option<u32>,
    pub sampler: Option<Sampler>,
    pub integrator: Option<super::Integrator>,
}

/// Why overrides do not make settings a render can use. The messages name
/// the settings by their `[render]` keys (the wire's field names); the
/// command line words the adaptive ones with its flags.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum SettingsError {
    /// A setting out of its range (the message names it).
    #[error("invalid render settings: {0}")]
    Invalid(String),
    /// The adaptive keys do not make adaptive settings (the message names
    /// the key).
    #[error("{0}")]
    Adaptive(String),
    /// `samples` given for an adaptive render.
    #[error(
        "samples does not apply to adaptive sampling (target_error, relative_error): give min_samples and max_samples"
    )]
    SamplesWithAdaptive,
    /// A sampler other than progressive given for an adaptive render.
    #[error(
        "sampler {} does not apply to adaptive sampling (target_error, relative_error), which places samples progressively",
        .0.name()
    )]
    SamplerWithAdaptive(Sampler),
}

impl RenderOverrides {
    /// `scene`'s settings with these overrides in their place, unchecked:
    /// for callers that check the result with their own messages (the
    /// scene parser names the file's line).
    pub(crate) fn over(&self, scene: &RenderSettings) -> RenderSettings {
        RenderSettings {
            width: self.width.unwrap_or(scene.width),
            height: self.height.unwrap_or(scene.height),
            samples: self.samples.unwrap_or(scene.samples),
            max_depth: self.max_depth.unwrap_or(scene.max_depth),
            sampler: self.sampler.unwrap_or(scene.sampler),
            integrator: self.integrator.unwrap_or(scene.integrator),
        }
    }

    /// The scene's settings with these overrides applied, validated.
    pub fn apply(&self, scene: &RenderSettings) -> Result<RenderSettings, SettingsError> {
        let s = self.over(scene);
        s.validate().map_err(SettingsError::Invalid)?;
        Ok(s)
    }

    /// What a render of `scene` traces with under these overrides and the
    /// adaptive keys `adaptive` (over the scene's own): the render
    /// settings, and the adaptive settings when the render is adaptive
    /// (then `samples` is `max_samples` and the sampler progressive, and
    /// overriding either is an error). The one place a render's settings
    /// are resolved and checked, for `tessera render` and for a job.
    pub fn resolve(
        &self,
        scene: &SceneDesc,
        adaptive: &AdaptiveSpec,
    ) -> Result<(RenderSettings, Option<AdaptiveSettings>), SettingsError> {
        let settings = self.apply(&scene.render)?;
        let Some(a) = scene
            .adaptive
            .resolve(adaptive)
            .map_err(SettingsError::Adaptive)?
        else {
            return Ok((settings, None));
        };
        if self.samples.is_some() {
            return Err(SettingsError::SamplesWithAdaptive);
        }
        if let Some(s) = self.sampler.filter(|&s| s != Sampler::Progressive) {
            return Err(SettingsError::SamplerWithAdaptive(s));
        }
        Ok((a.render_settings(settings), Some(a)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE: &str = "[camera]\nposition = [0, 1, -6]\nlook_at = [0, 1, 0]\n\n\
        [materials.red]\ndiffuse = [1, 0, 0]\n\n\
        [[objects]]\ntype = \"sphere\"\ncenter = [0, 1, 0]\nradius = 1\nmaterial = \"red\"\n";

    #[test]
    fn overrides_replace_what_they_give_and_are_validated() {
        let scene = RenderSettings::default();
        assert_eq!(RenderOverrides::default().apply(&scene), Ok(scene));
        let o = RenderOverrides {
            width: Some(64),
            sampler: Some(Sampler::Jittered),
            ..Default::default()
        };
        let s = o.apply(&scene).unwrap();
        assert_eq!((s.width, s.height, s.sampler), (64, 600, Sampler::Jittered));
        let bad = RenderOverrides {
            samples: Some(0),
            ..Default::default()
        };
        assert_eq!(
            bad.apply(&scene).unwrap_err().to_string(),
            "invalid render settings: samples must be in 1..=65536, got 0"
        );
    }

    #[test]
    fn adaptive_renders_refuse_samples_and_other_samplers() {
        let scene =
            SceneDesc::parse(&format!("[render]\ntarget_error = 0.01\n{SCENE}"), "t.toml").unwrap();
        let (s, a) = RenderOverrides::default()
            .resolve(&scene, &AdaptiveSpec::default())
            .unwrap();
        let a = a.unwrap();
        assert_eq!(
            (s.samples, s.sampler),
            (a.max_samples, Sampler::Progressive)
        );
        let samples = RenderOverrides {
            samples: Some(4),
            ..Default::default()
        };
        assert_eq!(
            samples.resolve(&scene, &AdaptiveSpec::default()),
            Err(SettingsError::SamplesWithAdaptive)
        );
        let grid = RenderOverrides {
            sampler: Some(Sampler::Grid),
            ..Default::default()
        };
        assert_eq!(
            grid.resolve(&scene, &AdaptiveSpec::default()),
            Err(SettingsError::SamplerWithAdaptive(Sampler::Grid))
        );
        let progressive = RenderOverrides {
            sampler: Some(Sampler::Progressive),
            ..Default::default()
        };
        assert!(
            progressive
                .resolve(&scene, &AdaptiveSpec::default())
                .is_ok()
        );
        // A uniform scene stays uniform, with the overrides as given.
        let uniform = SceneDesc::parse(SCENE, "t.toml").unwrap();
        assert_eq!(
            samples.resolve(&uniform, &AdaptiveSpec::default()),
            Ok((samples.apply(&uniform.render).unwrap(), None))
        );
    }
}
