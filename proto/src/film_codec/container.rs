//! The film container: a film's packed fields ([`super::Packed`], the
//! fields a result carries on the wire) behind a header of what the wire
//! carries beside them (rect, rays, the encoding), as the coordinator's
//! store keeps it; or, read only, the original layout earlier releases
//! stored. Its pixels are decoded by the same [`super::unpack_film`] as
//! the wire's.

use tracer_core::film::{Film, RayCounts, Rect, RunCost};

use crate::film_codec;

/// Marks a stored film in the compact layout: its first four bytes. In the
/// original layout they are the film's x, far below this (images are at
/// most `MAX_IMAGE_SIDE` = 32768 wide), so films stored by earlier versions
/// still decode.
pub const COMPACT_MAGIC: [u8; 4] = *b"TFC2";
/// The compact layout of an adaptive film: one more header byte, the
/// squares' width, and the sums of squares after the counts.
pub const ADAPTIVE_MAGIC: [u8; 4] = *b"TFA1";
/// An adaptive film with the runs it was rendered in ([`Film::runs`]):
/// the adaptive layout, then the runs (a u32 count, then each run's rect
/// as four u32, rays as u64 and samples as u32).
pub const RUNS_MAGIC: [u8; 4] = *b"TFR1";
/// Bytes of one run in the trailer.
const RUN_BYTES: usize = 16 + 8 + 4;
/// Bytes before the pixels: the magic, the rect, ray counts and the
/// non-finite count, then the encoding (sum bytes, uniform flag, count).
const COMPACT_HEADER: usize = 4 + 16 + 40 + 1 + 1 + 4;

/// A film for the store, in the compact layout of [`film_codec::pack`].
pub fn encode_film(f: &Film) -> Vec<u8> {
    EncodedFilm::of_film(f).to_vec()
}

/// The part of `film` inside `rect` (which lies inside it), with these ray
/// counts, for the store: no intermediate film.
pub fn encode_film_part(film: &Film, rect: Rect, rays: RayCounts, nonfinite: u64) -> Vec<u8> {
    EncodedFilm::of_part(film, rect, rays, nonfinite).to_vec()
}

/// A film in the store's compact layout, kept as its parts: the store's
/// writer copies them straight into the database's page (a GPU result is
/// tens of megabytes, and one more copy of it cost ~10 ms).
#[derive(Debug)]
pub struct EncodedFilm {
    header: Vec<u8>,
    packed: film_codec::Packed,
    squares: Vec<u8>,
    runs: Vec<u8>,
}

impl EncodedFilm {
    /// A film already in the compact layout (a result's fields as they came
    /// over the wire, checked by decoding them): a header, no re-encoding.
    /// `squares` (width, bytes) for adaptive films.
    pub fn new(
        rect: Rect,
        rays: RayCounts,
        nonfinite: u64,
        packed: film_codec::Packed,
        squares: Option<(u8, Vec<u8>)>,
    ) -> EncodedFilm {
        let mut header = Vec::with_capacity(COMPACT_HEADER + 1);
        // Adaptive films (sums of squares) are the compact layout with one
        // more header byte (the squares' width) and the squares at the end.
        header.extend_from_slice(if squares.is_some() {
            &ADAPTIVE_MAGIC
        } else {
            &COMPACT_MAGIC
        });
        for v in [rect.x, rect.y, rect.width, rect.height] {
            header.extend_from_slice(&v.to_le_bytes());
        }
        for v in [
            rays.primary,
            rays.shadow,
            rays.reflection,
            rays.refraction,
            nonfinite,
        ] {
            header.extend_from_slice(&v.to_le_bytes());
        }
        header.push(packed.sum_bytes);
        header.push(u8::from(packed.uniform_count.is_some()));
        header.extend_from_slice(&packed.uniform_count.unwrap_or(0).to_le_bytes());
        let squares = match squares {
            Some((n, bytes)) => {
                header.push(n);
                bytes
            }
            None => Vec::new(),
        };
        EncodedFilm {
            header,
            packed,
            squares,
            runs: Vec::new(),
        }
    }

    /// With the runs an adaptive film was rendered in (none: unchanged).
    pub fn with_runs(mut self, runs: &[RunCost]) -> EncodedFilm {
        if runs.is_empty() || !self.header.starts_with(&ADAPTIVE_MAGIC) {
            return self;
        }
        self.header[..4].copy_from_slice(&RUNS_MAGIC);
        let mut out = Vec::with_capacity(4 + runs.len() * RUN_BYTES);
        out.extend_from_slice(&(runs.len() as u32).to_le_bytes());
        for r in runs {
            for v in [r.rect.x, r.rect.y, r.rect.width, r.rect.height] {
                out.extend_from_slice(&v.to_le_bytes());
            }
            out.extend_from_slice(&r.rays.to_le_bytes());
            out.extend_from_slice(&r.samples.to_le_bytes());
        }
        self.runs = out;
        self
    }

    /// The part of `film` inside `rect` (which lies inside it), packed,
    /// with these ray counts: no intermediate film.
    pub fn of_part(film: &Film, rect: Rect, rays: RayCounts, nonfinite: u64) -> EncodedFilm {
        EncodedFilm::new(
            rect,
            rays,
            nonfinite,
            film_codec::pack_part(film, rect),
            film_codec::pack_squares_part(film, rect),
        )
    }

    /// A whole film, packed (with its sums of squares and runs if it has
    /// them).
    pub fn of_film(f: &Film) -> EncodedFilm {
        EncodedFilm::of_part(f, f.rect, f.rays, f.nonfinite).with_runs(&f.runs)
    }

    /// Bytes of the encoded film.
    pub fn len(&self) -> usize {
        self.parts().iter().map(|p| p.len()).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The encoded film's bytes, in five parts.
    pub fn parts(&self) -> [&[u8]; 5] {
        [
            &self.header,
            &self.packed.sums,
            &self.packed.counts,
            &self.squares,
            &self.runs,
        ]
    }

    /// Writes the encoded film into `out`, which is [`EncodedFilm::len`] long.
    pub fn write_to(&self, out: &mut [u8]) {
        let mut at = 0;
        for part in self.parts() {
            out[at..at + part.len()].copy_from_slice(part);
            at += part.len();
        }
        debug_assert_eq!(at, out.len());
    }

    pub fn to_vec(&self) -> Vec<u8> {
        let mut out = vec![0u8; self.len()];
        self.write_to(&mut out);
        out
    }
}

/// A stored film, in the compact layout or in the original one (56-byte
/// header, then 28 bytes a pixel) that earlier versions stored.
pub fn decode_film(b: &[u8]) -> Result<Film, String> {
    let with_runs = b.starts_with(&RUNS_MAGIC);
    let adaptive = with_runs || b.starts_with(&ADAPTIVE_MAGIC);
    let compact = adaptive || b.starts_with(&COMPACT_MAGIC);
    let header = match (compact, adaptive) {
        (_, true) => COMPACT_HEADER + 1,
        (true, false) => COMPACT_HEADER,
        (false, _) => 56,
    };
    if b.len() < header {
        return Err(format!(
            "{} bytes is shorter than the {header}-byte header",
            b.len()
        ));
    }
    let at = if compact { 4 } else { 0 };
    let u32_at = |i: usize| u32::from_le_bytes(b[at + i..at + i + 4].try_into().expect("4 bytes"));
    let u64_at = |i: usize| u64::from_le_bytes(b[at + i..at + i + 8].try_into().expect("8 bytes"));
    let rect = Rect::new(u32_at(0), u32_at(4), u32_at(8), u32_at(12));
    let rays = RayCounts {
        primary: u64_at(16),
        shadow: u64_at(24),
        reflection: u64_at(32),
        refraction: u64_at(40),
    };
    let nonfinite = u64_at(48);
    let encoding = if compact {
        film_codec::Encoding {
            sum_bytes: b[at + 56],
            uniform_count: (b[at + 57] != 0).then(|| u32_at(58)),
        }
    } else {
        film_codec::Encoding::ORIGINAL
    };
    let sums_len = encoding
        .sums_len(rect.area())
        .filter(|&n| n <= b.len() - header)
        .ok_or_else(|| {
            format!(
                "{} bytes is too short for a {}x{} film",
                b.len(),
                rect.width,
                rect.height
            )
        })?;
    let split = header + sums_len;
    // An adaptive film's squares follow its counts; other films end there.
    let (counts_end, squares) = if adaptive {
        let end = encoding
            .counts_len(rect.area())
            .map(|n| split + n)
            .filter(|&end| end <= b.len())
            .ok_or_else(|| format!("{} bytes is too short for the counts", b.len()))?;
        let width = u32::from(b[COMPACT_HEADER]);
        let squares_end = if with_runs {
            (rect.area() * 3)
                .checked_mul(width as usize)
                .map(|n| end + n)
                .filter(|&e| e <= b.len())
                .ok_or_else(|| format!("{} bytes is too short for the squares", b.len()))?
        } else {
            b.len()
        };
        (end, Some((width, &b[end..squares_end])))
    } else {
        (b.len(), None)
    };
    let mut film = film_codec::unpack_film(
        rect,
        encoding,
        &b[header..split],
        &b[split..counts_end],
        squares,
        rays,
        nonfinite,
    )
    .map_err(|e| e.to_string())?;
    if with_runs {
        let at = counts_end + squares.map_or(0, |(_, s)| s.len());
        film.runs = decode_runs(&b[at..])?;
        film.validate().map_err(|e| format!("its runs: {e}"))?;
    }
    Ok(film)
}

/// The runs' trailer of a [`RUNS_MAGIC`] film.
fn decode_runs(b: &[u8]) -> Result<Vec<RunCost>, String> {
    let n = b
        .get(..4)
        .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes")) as usize)
        .ok_or("the runs' count is missing")?;
    let body = &b[4..];
    if n.checked_mul(RUN_BYTES) != Some(body.len()) {
        return Err(format!(
            "{} bytes of runs for {n} runs of {RUN_BYTES} bytes",
            body.len()
        ));
    }
    Ok(body
        .chunks_exact(RUN_BYTES)
        .map(|c| {
            let u32_at = |i: usize| u32::from_le_bytes(c[i..i + 4].try_into().expect("4 bytes"));
            RunCost {
                rect: Rect::new(u32_at(0), u32_at(4), u32_at(8), u32_at(12)),
                rays: u64::from_le_bytes(c[16..24].try_into().expect("8 bytes")),
                samples: u32_at(24),
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An adaptive film's runs (the error-optimal mode's costs) are kept
    /// by the store's container, exactly; a cut trailer is refused.
    #[test]
    fn an_adaptive_films_runs_round_trip_in_the_container() {
        let rect = Rect::new(32, 8, 40, 16);
        let mut f = Film::with_squares(rect);
        f.counts.iter_mut().for_each(|c| *c = 3);
        f.squares.as_mut().unwrap()[7] = [1 << 90, 2, 3];
        f.runs = vec![
            RunCost {
                rect: Rect::new(32, 8, 32, 8),
                rays: u64::MAX - 5,
                samples: 3,
            },
            RunCost {
                rect: Rect::new(64, 16, 8, 8),
                rays: 17,
                samples: 3,
            },
        ];
        let bytes = encode_film(&f);
        assert!(bytes.starts_with(&RUNS_MAGIC));
        assert_eq!(decode_film(&bytes), Ok(f.clone()));
        assert_eq!(
            decode_film(&bytes[..bytes.len() - 1]),
            Err("55 bytes of runs for 2 runs of 28 bytes".into())
        );
        // A run outside the film is refused.
        f.runs[1].rect.x = 72;
        assert!(
            decode_film(&encode_film(&f))
                .unwrap_err()
                .starts_with("its runs")
        );
        // Without runs the film stays in the adaptive layout.
        f.runs.clear();
        assert!(encode_film(&f).starts_with(&ADAPTIVE_MAGIC));
    }

    /// One codec: a film's fields as a result carries them on the wire and
    /// the same fields in the store's container decode to the same film,
    /// uniform and adaptive; a wrong square width is refused the same way.
    #[test]
    fn the_wire_fields_and_the_stored_container_decode_alike() {
        let rect = Rect::new(3, 2, 5, 3);
        let mut f = Film::new(rect);
        for (i, (s, c)) in f.sums.iter_mut().zip(&mut f.counts).enumerate() {
            *s = [i as u64 * 1000, 7, i as u64];
            *c = 16;
        }
        f.rays = RayCounts {
            primary: 1,
            shadow: 2,
            reflection: 3,
            refraction: 4,
        };
        f.nonfinite = 5;
        let mut adaptive = f.clone();
        adaptive.squares = Some((0..15u128).map(|i| [i << 70, i, 1]).collect());
        for film in [f, adaptive] {
            let packed = film_codec::pack(&film);
            let squares = film_codec::pack_squares_part(&film, rect);
            // What the coordinator reads from a result's fields.
            let wire = film_codec::unpack_film(
                rect,
                film_codec::Encoding::from_wire(packed.sum_bytes.into(), packed.uniform_count)
                    .unwrap(),
                &packed.sums,
                &packed.counts,
                squares.as_ref().map(|(n, b)| (u32::from(*n), &b[..])),
                film.rays,
                film.nonfinite,
            )
            .unwrap();
            let stored = EncodedFilm::new(rect, film.rays, film.nonfinite, packed, squares);
            assert_eq!(wire, film);
            assert_eq!(decode_film(&stored.to_vec()), Ok(film));
        }
        assert_eq!(
            film_codec::unpack_film(
                rect,
                film_codec::Encoding::ORIGINAL,
                &[0; 15 * 24],
                &[0; 15 * 4],
                Some((300, &[][..])),
                RayCounts::default(),
                0
            ),
            Err(film_codec::FilmCodecError::SquareBytes(300))
        );
        assert_eq!(
            film_codec::Encoding::from_wire(9, None),
            Err(film_codec::FilmCodecError::SumBytes(9))
        );
    }
}
