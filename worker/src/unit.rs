//! A leased unit as the worker queues it, and a rendered one as it goes
//! back. The wire's `WorkUnit` becomes the shared
//! [`tessera_proto::LeasedUnit`] when it is leased (**API boundary**): the
//! render loop, the scene and frame caches and the renderers never see a
//! prost message.

use tessera_proto::{LeasedUnit, MalformedUnit, film_codec, pb};
use tracer_core::film::{Film, RayCounts, RunCost};

/// A unit this worker holds a lease on, as read from the wire: a unit
/// that came malformed is still held, and its failure sent back.
pub(crate) type Queued = Result<LeasedUnit, MalformedUnit>;

/// The lease of a queued unit, malformed or not.
pub(crate) fn lease_id(q: &Queued) -> &str {
    match q {
        Ok(u) => &u.lease_id,
        Err(m) => &m.lease_id,
    }
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
    /// Image-mode units rendered on the CPU: the runs of blocks with their
    /// rays.
    pub runs: Vec<RunCost>,
}

impl UnitFilm {
    pub fn of_film(film: &Film) -> Self {
        UnitFilm {
            packed: film_codec::pack(film),
            squares: film_codec::pack_squares_part(film, film.rect).map(|(n, b)| (n, b.into())),
            rays: film.rays,
            nonfinite: film.nonfinite,
            runs: film.runs.clone(),
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
            runs: Vec::new(),
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
        req.runs = self.runs.iter().map(|&r| r.into()).collect();
    }
}
