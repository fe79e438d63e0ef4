//! Conversions between protobuf messages and tracer-core types.

use tracer_core::film::{RayCounts, Rect, SampleRange, WorkRegion};
use tracer_core::render::Backend;
use tracer_core::sampling::Sampler;
use tracer_core::scene::RenderSettings;

use crate::pb;

/// A message from the wire that does not make a valid value.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ConvertError {
    #[error("missing field `{0}`")]
    Missing(&'static str),
    #[error("field `{field}`: {message}")]
    Invalid {
        field: &'static str,
        message: String,
    },
}

impl From<Rect> for pb::Rect {
    fn from(r: Rect) -> Self {
        pb::Rect {
            x: r.x,
            y: r.y,
            width: r.width,
            height: r.height,
        }
    }
}

impl From<pb::Rect> for Rect {
    fn from(r: pb::Rect) -> Self {
        Rect::new(r.x, r.y, r.width, r.height)
    }
}

impl From<SampleRange> for pb::SampleRange {
    fn from(s: SampleRange) -> Self {
        pb::SampleRange {
            start: s.start,
            end: s.end,
        }
    }
}

impl From<pb::SampleRange> for SampleRange {
    fn from(s: pb::SampleRange) -> Self {
        SampleRange::new(s.start, s.end)
    }
}

/// A work unit's region travels as three loose fields (`frame`, `rect`,
/// `samples`); these are the one place that reads and writes them.
impl pb::WorkUnit {
    /// The frame, pixels and samples the unit covers. A missing rect or
    /// sample range reads as empty (no pixels, no samples).
    pub fn region(&self) -> WorkRegion {
        WorkRegion {
            frame: self.frame,
            rect: self.rect.unwrap_or_default().into(),
            samples: self.samples.unwrap_or_default().into(),
        }
    }

    pub fn set_region(&mut self, r: WorkRegion) {
        self.frame = r.frame;
        self.rect = Some(r.rect.into());
        self.samples = Some(r.samples.into());
    }
}

impl From<RayCounts> for pb::RayCounts {
    fn from(r: RayCounts) -> Self {
        pb::RayCounts {
            primary: r.primary,
            shadow: r.shadow,
            reflection: r.reflection,
            refraction: r.refraction,
        }
    }
}

impl From<pb::RayCounts> for RayCounts {
    fn from(r: pb::RayCounts) -> Self {
        RayCounts {
            primary: r.primary,
            shadow: r.shadow,
            reflection: r.reflection,
            refraction: r.refraction,
        }
    }
}

impl From<Sampler> for pb::Sampler {
    fn from(s: Sampler) -> Self {
        match s {
            Sampler::Grid => pb::Sampler::Grid,
            Sampler::Jittered => pb::Sampler::Jittered,
            Sampler::Progressive => pb::Sampler::Progressive,
        }
    }
}

/// `None` for UNSPECIFIED (and unknown values, which prost maps to it).
pub fn sampler_from_pb(v: i32) -> Option<Sampler> {
    match pb::Sampler::try_from(v).unwrap_or(pb::Sampler::Unspecified) {
        pb::Sampler::Grid => Some(Sampler::Grid),
        pb::Sampler::Jittered => Some(Sampler::Jittered),
        pb::Sampler::Progressive => Some(Sampler::Progressive),
        pb::Sampler::Unspecified => None,
    }
}

impl From<Backend> for pb::Backend {
    fn from(b: Backend) -> Self {
        match b {
            Backend::Cpu => pb::Backend::Cpu,
            Backend::Gpu => pb::Backend::Gpu,
        }
    }
}

/// `None` for UNSPECIFIED (and unknown values, which prost maps to it).
pub fn backend_from_pb(v: i32) -> Option<Backend> {
    match pb::Backend::try_from(v).unwrap_or(pb::Backend::Unspecified) {
        pb::Backend::Cpu => Some(Backend::Cpu),
        pb::Backend::Gpu => Some(Backend::Gpu),
        pb::Backend::Unspecified => None,
    }
}

impl From<RenderSettings> for pb::RenderSettings {
    fn from(s: RenderSettings) -> Self {
        pb::RenderSettings {
            width: s.width,
            height: s.height,
            samples: s.samples,
            max_depth: s.max_depth,
            sampler: pb::Sampler::from(s.sampler) as i32,
        }
    }
}

impl TryFrom<pb::RenderSettings> for RenderSettings {
    type Error = ConvertError;
    fn try_from(s: pb::RenderSettings) -> Result<Self, ConvertError> {
        let sampler = sampler_from_pb(s.sampler).ok_or(ConvertError::Invalid {
            field: "settings.sampler",
            message: "must be GRID, JITTERED or PROGRESSIVE".into(),
        })?;
        let out = RenderSettings {
            width: s.width,
            height: s.height,
            samples: s.samples,
            max_depth: s.max_depth,
            sampler,
        };
        out.validate().map_err(|message| ConvertError::Invalid {
            field: "settings",
            message,
        })?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_round_trip_and_validate() {
        let s = RenderSettings {
            width: 64,
            height: 48,
            samples: 9,
            max_depth: 3,
            sampler: Sampler::Jittered,
        };
        assert_eq!(RenderSettings::try_from(pb::RenderSettings::from(s)), Ok(s));
        let mut bad = pb::RenderSettings::from(s);
        bad.width = 0;
        assert!(matches!(
            RenderSettings::try_from(bad),
            Err(ConvertError::Invalid {
                field: "settings",
                ..
            })
        ));
        let mut bad = pb::RenderSettings::from(s);
        bad.sampler = 0;
        assert!(RenderSettings::try_from(bad).is_err());
    }

    #[test]
    fn a_work_units_region_round_trips_and_missing_fields_read_as_empty() {
        let r = WorkRegion::new(7, Rect::new(64, 128, 32, 16), SampleRange::new(8, 24));
        let mut unit = pb::WorkUnit::default();
        unit.set_region(r);
        assert_eq!(unit.frame, 7);
        assert_eq!(unit.region(), r);
        let empty = pb::WorkUnit::default().region();
        assert_eq!(empty.rect.area(), 0);
        assert!(empty.samples.is_empty());
    }

    #[test]
    fn backend_round_trip() {
        for b in [Backend::Cpu, Backend::Gpu] {
            assert_eq!(backend_from_pb(pb::Backend::from(b) as i32), Some(b));
        }
        assert_eq!(backend_from_pb(pb::Backend::Unspecified as i32), None);
        assert_eq!(backend_from_pb(99), None);
    }
}
