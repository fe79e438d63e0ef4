//! A leased unit as the worker renders it. The wire's `WorkUnit` is
//! converted here when it is leased (**API boundary**): the render loop,
//! the scene and frame caches and the renderers see only these types,
//! never a prost message.

use std::collections::BTreeMap;

use tessera_proto::{film_codec, pb};
use tracer_core::adaptive::BlockMask;
use tracer_core::film::{Film, RayCounts, WorkRegion};
use tracer_core::scene::RenderSettings;

/// A unit this worker holds a lease on.
#[derive(Debug)]
pub(crate) struct LeasedUnit {
    pub lease_id: String,
    /// The frame, pixels and samples to render.
    pub region: WorkRegion,
    /// What rendering needs, or why the unit cannot be rendered (it came
    /// malformed): sent back as the unit's failure, which the coordinator
    /// counts like any other.
    pub work: Result<UnitWork, String>,
    /// The job's work units the lease covers (counted as done on acceptance).
    pub units: u64,
}

/// A rendered unit as it goes on the wire: packed once, where it was
/// rendered, so that each send attempt clones it for free (its fields are
/// shared buffers; a GPU unit is megabytes).
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct UnitFilm {
    pub packed: film_codec::Packed,
    /// Adaptive units: the sums of squares' width and bytes.
    pub squares: Option<(u8, film_codec::Bytes)>,
    pub rays: RayCounts,
    pub nonfinite: u64,
}

impl UnitFilm {
    pub fn of_film(film: &Film) -> Self {
        UnitFilm {
            packed: film_codec::pack(film),
            squares: film_codec::pack_squares_part(film, film.rect).map(|(n, b)| (n, b.into())),
            rays: film.rays,
            nonfinite: film.nonfinite,
        }
    }

    /// A GPU unit packed on the GPU: the same bytes as
    /// [`UnitFilm::of_film`] of its film.
    #[cfg(feature = "gpu")]
    pub fn of_gpu(p: tracer_core::render::gpu::PackedSums) -> Self {
        UnitFilm {
            packed: film_codec::Packed {
                sum_bytes: p.sum_bytes,
                uniform_count: Some(p.samples),
                sums: p.sums.into(),
                counts: film_codec::Bytes::new(),
            },
            squares: None,
            rays: p.rays,
            nonfinite: p.nonfinite,
        }
    }

    /// The unit's fields of a result message.
    pub fn fill(&self, req: &mut pb::SubmitResultRequest) {
        req.sum_bytes = self.packed.sum_bytes.into();
        req.uniform_count = self.packed.uniform_count;
        req.sums = self.packed.sums.clone();
        req.counts = self.packed.counts.clone();
        if let Some((n, squares)) = &self.squares {
            req.square_bytes = (*n).into();
            req.squares = squares.clone();
        }
        req.rays = Some(self.rays.into());
        req.nonfinite = self.nonfinite;
    }
}

/// What rendering a unit needs besides its region.
#[derive(Debug)]
pub(crate) struct UnitWork {
    pub job: JobInfo,
    /// Adaptive jobs: the blocks of the region's rect this round samples.
    pub active: Option<BlockMask>,
}

/// The job a unit belongs to, as a worker needs it.
#[derive(Debug)]
pub(crate) struct JobInfo {
    pub job_id: String,
    /// The scene file's name, for messages.
    pub scene_name: String,
    /// SHA-256 of the scene TOML.
    pub scene_sha256: String,
    /// Name -> SHA-256 of the files the scene references, in name order.
    pub files: BTreeMap<String, String>,
    pub settings: RenderSettings,
}

impl From<pb::WorkUnit> for LeasedUnit {
    fn from(u: pb::WorkUnit) -> Self {
        let region = u.region();
        let work = u
            .job
            .ok_or_else(|| "work unit without job context".to_string())
            .and_then(JobInfo::try_from)
            .and_then(|job| {
                let active = u
                    .adaptive
                    .then(|| BlockMask::from_bytes(region.rect, &u.active_blocks))
                    .transpose()
                    .map_err(|e| e.to_string())?;
                Ok(UnitWork { job, active })
            });
        LeasedUnit {
            lease_id: u.lease_id,
            region,
            work,
            units: u.units.max(1) as u64,
        }
    }
}

impl TryFrom<pb::JobContext> for JobInfo {
    type Error = String;
    fn try_from(j: pb::JobContext) -> Result<Self, String> {
        let settings =
            RenderSettings::try_from(j.settings.unwrap_or_default()).map_err(|e| e.to_string())?;
        Ok(JobInfo {
            job_id: j.job_id,
            scene_name: j.scene_name,
            scene_sha256: j.scene_sha256,
            files: j.assets.into_iter().collect(),
            settings,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracer_core::film::{Rect, SampleRange};
    use tracer_core::sampling::Sampler;

    fn settings() -> RenderSettings {
        RenderSettings {
            width: 64,
            height: 32,
            samples: 4,
            max_depth: 3,
            sampler: Sampler::Grid,
            integrator: Default::default(),
        }
    }

    fn wire_unit() -> pb::WorkUnit {
        let mut u = pb::WorkUnit {
            lease_id: "l1".into(),
            job: Some(pb::JobContext {
                job_id: "j1".into(),
                scene_name: "s.toml".into(),
                scene_sha256: "ab".into(),
                assets: [("m.obj".to_string(), "cd".to_string())].into(),
                settings: Some(settings().into()),
            }),
            ..Default::default()
        };
        u.set_region(WorkRegion::new(
            2,
            Rect::new(16, 8, 32, 16),
            SampleRange::new(0, 4),
        ));
        u
    }

    #[test]
    fn a_wire_unit_becomes_the_workers_own() {
        let u = LeasedUnit::from(wire_unit());
        assert_eq!(u.lease_id, "l1");
        assert_eq!(
            u.region,
            WorkRegion::new(2, Rect::new(16, 8, 32, 16), SampleRange::new(0, 4))
        );
        let work = u.work.expect("well-formed");
        assert_eq!(work.job.job_id, "j1");
        assert_eq!(work.job.files["m.obj"], "cd");
        assert_eq!(work.job.settings, settings());
        assert!(work.active.is_none());
    }

    #[test]
    fn a_malformed_wire_unit_keeps_its_lease_and_says_why() {
        let mut w = wire_unit();
        w.job = None;
        let u = LeasedUnit::from(w);
        assert_eq!(u.lease_id, "l1");
        assert_eq!(u.work.unwrap_err(), "work unit without job context");
        let mut w = wire_unit();
        w.job.as_mut().unwrap().settings.as_mut().unwrap().width = 0;
        assert!(LeasedUnit::from(w).work.is_err());
        let mut w = wire_unit();
        w.adaptive = true;
        w.active_blocks = vec![0xff; 99];
        assert!(LeasedUnit::from(w).work.is_err());
    }
}
