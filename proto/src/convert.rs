//! Conversions between protobuf messages and Rust types (tracer-core's
//! and [`JobSpec`]): the one place each wire message meets its Rust shape.

use tracer_core::adaptive::{AdaptiveMode, AdaptiveSpec, BlockMask};
use tracer_core::film::{RayCounts, Rect, RunCost, SampleRange, WorkRegion};
use tracer_core::render::Backend;
use tracer_core::sampling::Sampler;
use tracer_core::scene::{Integrator, RenderOverrides, RenderSettings};

use crate::job::JobSpec;
use crate::lease::{LeasedJob, LeasedUnit, MalformedUnit};
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

impl From<RunCost> for pb::RunCost {
    fn from(r: RunCost) -> Self {
        pb::RunCost {
            rect: Some(r.rect.into()),
            rays: r.rays,
            samples: r.samples,
        }
    }
}

impl From<&pb::RunCost> for RunCost {
    fn from(r: &pb::RunCost) -> Self {
        RunCost {
            rect: r.rect.unwrap_or_default().into(),
            rays: r.rays,
            samples: r.samples,
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

impl From<LeasedUnit> for pb::WorkUnit {
    fn from(l: LeasedUnit) -> Self {
        let j = l.job;
        let mut unit = pb::WorkUnit {
            lease_id: l.lease_id,
            job: Some(pb::JobContext {
                job_id: j.job_id,
                scene_name: j.scene_name,
                scene_sha256: j.scene_sha256,
                assets: j.files.into_iter().collect(),
                settings: Some(j.settings.into()),
            }),
            adaptive: l.active.is_some(),
            active_blocks: l.active.map(|m| m.to_bytes()).unwrap_or_default(),
            block_samples: l
                .ranges
                .map(|r| r.into_iter().map(Into::into).collect())
                .unwrap_or_default(),
            units: l.units,
            ..Default::default()
        };
        unit.set_region(l.region);
        unit
    }
}

/// A worker's reading of a leased unit. A unit that does not decode keeps
/// its lease, region and unit count, so its failure can be reported.
impl TryFrom<pb::WorkUnit> for LeasedUnit {
    type Error = MalformedUnit;
    fn try_from(u: pb::WorkUnit) -> Result<Self, MalformedUnit> {
        let region = u.region();
        // 0 from an older coordinator: count 1.
        let units = u.units.max(1);
        let decoded = u
            .job
            .ok_or_else(|| "work unit without job context".to_string())
            .and_then(|j| {
                let settings = RenderSettings::try_from(j.settings.unwrap_or_default())
                    .map_err(|e| e.to_string())?;
                Ok(LeasedJob {
                    job_id: j.job_id,
                    scene_name: j.scene_name,
                    scene_sha256: j.scene_sha256,
                    files: j.assets.into_iter().collect(),
                    settings,
                })
            })
            .and_then(|job| {
                let active = u
                    .adaptive
                    .then(|| BlockMask::from_bytes(region.rect, &u.active_blocks))
                    .transpose()
                    .map_err(|e| e.to_string())?;
                let ranges = block_ranges(&u.block_samples, active.as_ref(), region)?;
                Ok((job, active, ranges))
            });
        match decoded {
            Ok((job, active, ranges)) => Ok(LeasedUnit {
                lease_id: u.lease_id,
                job,
                region,
                active,
                ranges,
                units,
            }),
            Err(why) => Err(MalformedUnit {
                lease_id: u.lease_id,
                region,
                units,
                why,
            }),
        }
    }
}

/// A unit's per-block ranges (`WorkUnit.block_samples`), checked against
/// its active blocks and sample range: `None` where there are none.
fn block_ranges(
    wire: &[pb::SampleRange],
    active: Option<&BlockMask>,
    region: WorkRegion,
) -> Result<Option<Vec<SampleRange>>, String> {
    if wire.is_empty() {
        return Ok(None);
    }
    let Some(mask) = active else {
        return Err("block_samples in a unit that is not adaptive".into());
    };
    if wire.len() != mask.active.len() {
        return Err(format!(
            "block_samples has {} ranges, the rect has {} blocks",
            wire.len(),
            mask.active.len()
        ));
    }
    let hull = region.samples;
    let ranges: Vec<SampleRange> = wire.iter().map(|&r| r.into()).collect();
    for (i, (r, &on)) in ranges.iter().zip(&mask.active).enumerate() {
        if r.start > r.end || (!r.is_empty() && (r.start < hull.start || r.end > hull.end)) {
            return Err(format!(
                "block {i}'s samples {}..{} do not lie in the unit's {}..{}",
                r.start, r.end, hull.start, hull.end
            ));
        }
        if r.is_empty() == on {
            return Err(format!(
                "block {i} is {} but its samples are {}..{}",
                if on { "active" } else { "inactive" },
                r.start,
                r.end
            ));
        }
    }
    Ok(Some(ranges))
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
            integrator: integrator_to_pb(s.integrator) as i32,
        }
    }
}

fn integrator_to_pb(i: Integrator) -> pb::Integrator {
    match i {
        Integrator::Whitted => pb::Integrator::Whitted,
        Integrator::Path => pb::Integrator::Path,
    }
}

/// The integrator of a wire value; `None` for UNSPECIFIED or unknown.
pub fn integrator_from_pb(v: i32) -> Option<Integrator> {
    match pb::Integrator::try_from(v).unwrap_or(pb::Integrator::Unspecified) {
        pb::Integrator::Whitted => Some(Integrator::Whitted),
        pb::Integrator::Path => Some(Integrator::Path),
        pb::Integrator::Unspecified => None,
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
            // Senders older than the path tracer leave it UNSPECIFIED: Whitted.
            integrator: integrator_from_pb(s.integrator).unwrap_or_default(),
        };
        out.validate().map_err(|message| ConvertError::Invalid {
            field: "settings",
            message,
        })?;
        Ok(out)
    }
}

/// The render settings of a `RenderOverrides` message (its adaptive keys
/// are [`AdaptiveSpec`]'s). Unchecked: the coordinator validates them with
/// the scene they apply to ([`RenderOverrides::resolve`]).
impl From<&pb::RenderOverrides> for RenderOverrides {
    fn from(o: &pb::RenderOverrides) -> Self {
        RenderOverrides {
            width: o.width,
            height: o.height,
            samples: o.samples,
            max_depth: o.max_depth,
            sampler: sampler_from_pb(o.sampler),
            integrator: integrator_from_pb(o.integrator),
        }
    }
}

/// The adaptive keys of a `RenderOverrides` message.
impl From<&pb::RenderOverrides> for AdaptiveSpec {
    fn from(o: &pb::RenderOverrides) -> Self {
        AdaptiveSpec {
            target_error: o.target_error,
            relative_error: o.relative_error,
            min_samples: o.min_samples,
            max_samples: o.max_samples,
            mode: adaptive_mode_from_pb(o.adaptive_mode),
        }
    }
}

/// Overrides and the adaptive keys given with them, as one message.
impl From<(RenderOverrides, AdaptiveSpec)> for pb::RenderOverrides {
    fn from((o, a): (RenderOverrides, AdaptiveSpec)) -> Self {
        pb::RenderOverrides {
            width: o.width,
            height: o.height,
            samples: o.samples,
            max_depth: o.max_depth,
            sampler: o
                .sampler
                .map_or(pb::Sampler::Unspecified, pb::Sampler::from) as i32,
            integrator: o
                .integrator
                .map_or(pb::Integrator::Unspecified, integrator_to_pb)
                as i32,
            target_error: a.target_error,
            relative_error: a.relative_error,
            min_samples: a.min_samples,
            max_samples: a.max_samples,
            adaptive_mode: a
                .mode
                .map_or(pb::AdaptiveMode::Unspecified, adaptive_mode_to_pb)
                as i32,
        }
    }
}

/// A wire `AdaptiveMode`; `None` where it is unspecified (or unknown: a
/// newer peer's).
pub fn adaptive_mode_from_pb(m: i32) -> Option<AdaptiveMode> {
    match pb::AdaptiveMode::try_from(m) {
        Ok(pb::AdaptiveMode::Pixel) => Some(AdaptiveMode::Pixel),
        Ok(pb::AdaptiveMode::Image) => Some(AdaptiveMode::Image),
        _ => None,
    }
}

pub fn adaptive_mode_to_pb(m: AdaptiveMode) -> pb::AdaptiveMode {
    match m {
        AdaptiveMode::Pixel => pb::AdaptiveMode::Pixel,
        AdaptiveMode::Image => pb::AdaptiveMode::Image,
    }
}

/// The job's message without its files: the scene's text and its other
/// files (`scene`, `assets`, `files`) are the sender's to add.
impl From<JobSpec> for pb::JobSpec {
    fn from(j: JobSpec) -> Self {
        pb::JobSpec {
            name: j.name,
            scene_name: j.scene_name,
            scene: Vec::new(),
            assets: Vec::new(),
            overrides: Some((j.overrides, j.adaptive).into()),
            first_frame: j.first_frame,
            last_frame: j.last_frame,
            priority: j.priority,
            tile_size: j.tile_size.unwrap_or(0),
            samples_per_unit: j.samples_per_unit.unwrap_or(0),
            max_attempts: j.max_attempts.unwrap_or(0),
            files: Default::default(),
            requirements: j.requirements,
            after: j.after,
            on_done: j.on_done,
            blocklist_after: j.blocklist_after,
            blocklist_seconds: j.blocklist_seconds,
        }
    }
}

/// What a job message asks for, its files aside. The wire's defaults
/// become Rust's: 0 is `None`, an empty scene name `scene.toml`.
impl From<&pb::JobSpec> for JobSpec {
    fn from(j: &pb::JobSpec) -> Self {
        let o = j.overrides.unwrap_or_default();
        let given = |v: u32| (v != 0).then_some(v);
        JobSpec {
            name: j.name.clone(),
            scene_name: if j.scene_name.is_empty() {
                "scene.toml".into()
            } else {
                j.scene_name.clone()
            },
            overrides: (&o).into(),
            adaptive: (&o).into(),
            first_frame: j.first_frame,
            last_frame: j.last_frame,
            priority: j.priority,
            tile_size: given(j.tile_size),
            samples_per_unit: given(j.samples_per_unit),
            max_attempts: given(j.max_attempts),
            requirements: j.requirements.clone(),
            after: j.after.clone(),
            on_done: j.on_done.clone(),
            blocklist_after: j.blocklist_after,
            blocklist_seconds: j.blocklist_seconds,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leased_unit() -> LeasedUnit {
        LeasedUnit {
            lease_id: "l1".into(),
            job: LeasedJob {
                job_id: "j1".into(),
                scene_name: "s.toml".into(),
                scene_sha256: "ab".into(),
                files: [("m.obj".to_string(), "cd".to_string())].into(),
                settings: RenderSettings {
                    width: 64,
                    height: 32,
                    samples: 4,
                    max_depth: 3,
                    sampler: Sampler::Grid,
                    integrator: Integrator::Path,
                },
            },
            region: WorkRegion::new(2, Rect::new(16, 8, 32, 16), SampleRange::new(0, 4)),
            active: None,
            ranges: None,
            units: 3,
        }
    }

    #[test]
    fn leased_units_round_trip_uniform_and_adaptive() {
        let l = leased_unit();
        assert_eq!(
            LeasedUnit::try_from(pb::WorkUnit::from(l.clone())),
            Ok(l.clone())
        );
        let mut mask = BlockMask::none(l.region.rect);
        mask.active[1] = true;
        let adaptive = LeasedUnit {
            active: Some(mask.clone()),
            ..l.clone()
        };
        assert_eq!(
            LeasedUnit::try_from(pb::WorkUnit::from(adaptive.clone())),
            Ok(adaptive.clone())
        );
        // The image mode: each block its own range inside the unit's.
        let mut ranges = vec![SampleRange::new(0, 0); mask.active.len()];
        ranges[1] = SampleRange::new(1, 3);
        let ranged = LeasedUnit {
            ranges: Some(ranges.clone()),
            ..adaptive.clone()
        };
        assert_eq!(
            LeasedUnit::try_from(pb::WorkUnit::from(ranged.clone())),
            Ok(ranged.clone())
        );
        // Ranges that disagree with the mask or the unit's range are refused.
        let why = |ranges: Vec<SampleRange>| {
            LeasedUnit::try_from(pb::WorkUnit::from(LeasedUnit {
                ranges: Some(ranges),
                ..adaptive.clone()
            }))
            .unwrap_err()
            .why
        };
        let mut r = ranges.clone();
        r[1] = SampleRange::new(2, 5);
        assert_eq!(
            why(r),
            "block 1's samples 2..5 do not lie in the unit's 0..4"
        );
        let mut r = ranges.clone();
        r[0] = SampleRange::new(0, 1);
        assert_eq!(why(r), "block 0 is inactive but its samples are 0..1");
        assert_eq!(
            why(ranges[..2].to_vec()),
            "block_samples has 2 ranges, the rect has 8 blocks"
        );
    }

    #[test]
    fn a_malformed_unit_keeps_its_lease_region_and_count_and_says_why() {
        let l = leased_unit();
        let malformed = |why: &str| MalformedUnit {
            lease_id: "l1".into(),
            region: l.region,
            units: 3,
            why: why.into(),
        };
        let mut w = pb::WorkUnit::from(l.clone());
        w.job = None;
        assert_eq!(
            LeasedUnit::try_from(w),
            Err(malformed("work unit without job context"))
        );
        let mut w = pb::WorkUnit::from(l.clone());
        w.job.as_mut().unwrap().settings.as_mut().unwrap().width = 0;
        let e = LeasedUnit::try_from(w).unwrap_err();
        assert_eq!((e.lease_id.as_str(), e.units), ("l1", 3));
        assert!(e.why.contains("width"), "{}", e.why);
        let mut w = pb::WorkUnit::from(l.clone());
        w.adaptive = true;
        w.active_blocks = vec![0xff; 99];
        assert_eq!(LeasedUnit::try_from(w).unwrap_err().lease_id, "l1");
        // An older coordinator's 0 counts as one unit.
        let mut w = pb::WorkUnit::from(l);
        w.units = 0;
        assert_eq!(LeasedUnit::try_from(w).map(|u| u.units), Ok(1));
    }

    #[test]
    fn job_specs_round_trip() {
        let spec = JobSpec {
            name: "j".into(),
            scene_name: "s.toml".into(),
            overrides: RenderOverrides {
                width: Some(64),
                height: None,
                samples: Some(9),
                max_depth: Some(0),
                sampler: Some(Sampler::Progressive),
                integrator: None,
            },
            adaptive: AdaptiveSpec {
                target_error: Some(0.01),
                relative_error: None,
                min_samples: Some(4),
                max_samples: None,
                mode: Some(AdaptiveMode::Image),
            },
            first_frame: 2,
            last_frame: 5,
            priority: -3,
            tile_size: Some(32),
            samples_per_unit: None,
            max_attempts: Some(1),
            requirements: vec!["backend=gpu".into(), "gpu_memory_gb>=40".into()],
            after: vec!["j0123456789".into()],
            on_done: vec!["http://127.0.0.1:9/hook".into()],
            blocklist_after: Some(0),
            blocklist_seconds: Some(60.0),
        };
        let wire = pb::JobSpec::from(spec.clone());
        assert_eq!(wire.samples_per_unit, 0);
        assert_eq!(JobSpec::from(&wire), spec);
        // The wire's defaults: nothing given is all `None`.
        let empty = JobSpec::from(&pb::JobSpec::default());
        assert_eq!(empty.scene_name, "scene.toml");
        assert_eq!(empty.overrides, RenderOverrides::default());
        assert_eq!(empty.adaptive, AdaptiveSpec::default());
        assert_eq!(
            (empty.tile_size, empty.samples_per_unit, empty.max_attempts),
            (None, None, None)
        );
        // An unknown sampler keeps the scene's, as UNSPECIFIED does.
        let mut odd = pb::JobSpec::from(spec);
        odd.overrides.as_mut().unwrap().sampler = 99;
        assert_eq!(JobSpec::from(&odd).overrides.sampler, None);
    }

    #[test]
    fn settings_round_trip_and_validate() {
        let s = RenderSettings {
            width: 64,
            height: 48,
            samples: 9,
            max_depth: 3,
            sampler: Sampler::Jittered,
            integrator: Default::default(),
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
    fn the_integrator_travels_and_older_senders_mean_whitted() {
        let path = RenderSettings {
            integrator: Integrator::Path,
            ..RenderSettings::default()
        };
        let wire = pb::RenderSettings::from(path);
        assert_eq!(wire.integrator, pb::Integrator::Path as i32);
        assert_eq!(RenderSettings::try_from(wire), Ok(path));
        // A sender that predates field 140 leaves it 0 (UNSPECIFIED).
        let old = pb::RenderSettings {
            integrator: 0,
            ..wire
        };
        assert_eq!(
            RenderSettings::try_from(old).map(|s| s.integrator),
            Ok(Integrator::Whitted)
        );
        // Overrides: UNSPECIFIED keeps the scene's, PATH overrides it.
        let o = RenderOverrides {
            integrator: Some(Integrator::Path),
            ..RenderOverrides::default()
        };
        let wire = pb::RenderOverrides::from((o, AdaptiveSpec::default()));
        assert_eq!(RenderOverrides::from(&wire), o);
        assert_eq!(
            RenderOverrides::from(&pb::RenderOverrides::default()).integrator,
            None
        );
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
