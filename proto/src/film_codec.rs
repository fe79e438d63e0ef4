//! Films on the wire and in the coordinator's store: the one film codec.
//!
//! Sums are fixed-point (exact) and stay exact in every encoding. The
//! original layout is R, G, B sums as little-endian `u64` per pixel and a
//! little-endian `u32` sample count per pixel (28 bytes a pixel). The
//! compact layout ([`Encoding`]) keeps only the low bytes every sum of the
//! film needs (a 64-sample film of radiance below 2^8 needs 5 of 8), and
//! one count for a film whose pixels all have the same number of samples,
//! as every result of a sample range does: 15 bytes a pixel instead of 28
//! for a 1080p frame at 64 samples.

pub use prost::bytes::Bytes;
use rayon::prelude::*;
use tracer_core::film::{Film, RayCounts, Rect};

mod container;
pub use container::{
    ADAPTIVE_MAGIC, COMPACT_MAGIC, EncodedFilm, decode_film, encode_film, encode_film_part,
};

/// Bytes per pixel of the `sums` field.
pub const SUM_BYTES: usize = 24;
/// Bytes per pixel of the `counts` field.
pub const COUNT_BYTES: usize = 4;

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum FilmCodecError {
    #[error(
        "sums field has {got} bytes, expected {expected} ({SUM_BYTES} per pixel of a {width}x{height} rect)"
    )]
    SumsSize {
        got: usize,
        expected: usize,
        width: u32,
        height: u32,
    },
    #[error(
        "counts field has {got} bytes, expected {expected} ({COUNT_BYTES} per pixel of a {width}x{height} rect)"
    )]
    CountsSize {
        got: usize,
        expected: usize,
        width: u32,
        height: u32,
    },
    #[error("a {width}x{height} rect is too large for a film ({SUM_BYTES} bytes a pixel)")]
    TooLarge { width: u32, height: u32 },
    #[error("sum_bytes must be 1 to 8, got {0}")]
    SumBytes(u32),
    #[error("square_bytes must be 1 to 16, got {0}")]
    SquareBytes(u32),
    #[error(
        "squares field has {got} bytes, expected {expected} (3 x {square_bytes} per pixel of a {width}x{height} rect)"
    )]
    SquaresSize {
        got: usize,
        expected: usize,
        square_bytes: u8,
        width: u32,
        height: u32,
    },
}

/// Films of at least this many pixels pack and unpack in parallel: a GPU
/// worker's results are up to 2^18 pixels each, several megabytes.
const PARALLEL_PIXELS: usize = 1 << 16;

/// How a film's pixels are laid out in bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Encoding {
    /// Little-endian bytes of each R, G, B sum, 1 to 8 (8: the original layout).
    pub sum_bytes: u8,
    /// `Some(n)`: every pixel has `n` samples and there is no counts field.
    pub uniform_count: Option<u32>,
}

impl Encoding {
    /// The original layout: 8-byte sums, a 4-byte count per pixel.
    pub const ORIGINAL: Encoding = Encoding {
        sum_bytes: 8,
        uniform_count: None,
    };

    /// The encoding a result's `sum_bytes` and `uniform_count` fields name
    /// (`sum_bytes` 0: the original layout, of releases before the compact one).
    pub fn from_wire(
        sum_bytes: u32,
        uniform_count: Option<u32>,
    ) -> Result<Encoding, FilmCodecError> {
        match sum_bytes {
            0 => Ok(Encoding::ORIGINAL),
            n @ 1..=8 => Ok(Encoding {
                sum_bytes: n as u8,
                uniform_count,
            }),
            n => Err(FilmCodecError::SumBytes(n)),
        }
    }

    /// Bytes of the sums field for `pixels` pixels (`None` on overflow).
    pub fn sums_len(self, pixels: usize) -> Option<usize> {
        pixels.checked_mul(3 * self.sum_bytes as usize)
    }

    /// Bytes of the counts field for `pixels` pixels (`None` on overflow).
    pub fn counts_len(self, pixels: usize) -> Option<usize> {
        match self.uniform_count {
            Some(_) => Some(0),
            None => pixels.checked_mul(COUNT_BYTES),
        }
    }
}

/// A film's pixels in the compact layout: its encoding and the two fields.
/// The fields are [`Bytes`], as in the wire's message: a result's bytes go
/// from the worker's packing to the socket, and from the coordinator's
/// receive buffer to its store, without a copy (a GPU result is tens of
/// megabytes).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Packed {
    pub sum_bytes: u8,
    pub uniform_count: Option<u32>,
    pub sums: Bytes,
    pub counts: Bytes,
}

impl Packed {
    pub fn encoding(&self) -> Encoding {
        Encoding {
            sum_bytes: self.sum_bytes,
            uniform_count: self.uniform_count,
        }
    }
}

/// Rows of `rect` (inside `film.rect`) as ranges of `film`'s pixel indices.
fn rows(film: &Film, rect: Rect) -> impl Iterator<Item = std::ops::Range<usize>> + '_ {
    let w = rect.width as usize;
    (0..rect.height).map(move |row| {
        let start =
            ((rect.y - film.rect.y + row) * film.rect.width + (rect.x - film.rect.x)) as usize;
        start..start + w
    })
}

/// The part of `film` inside `rect` (which must lie inside it) in the
/// compact layout, with no intermediate film.
pub fn pack_part(film: &Film, rect: Rect) -> Packed {
    assert!(
        film.rect.contains(&rect),
        "{rect:?} outside {:?}",
        film.rect
    );
    let parallel = rect.area() >= PARALLEL_PIXELS;
    let count = rows(film, rect)
        .next()
        .filter(|_| rect.area() > 0)
        .map(|r| film.counts[r.start]);
    // The largest sum's bits, and whether every count is the first's.
    let scan = |r: std::ops::Range<usize>| {
        let max = film.sums[r.clone()]
            .iter()
            .fold(0u64, |m, s| m | s[0] | s[1] | s[2]);
        let uniform = film.counts[r].iter().all(|&c| Some(c) == count);
        (max, uniform)
    };
    let (max, uniform) = if parallel {
        let rows: Vec<_> = rows(film, rect).collect();
        rows.into_par_iter()
            .map(scan)
            .reduce(|| (0, true), |a, b| (a.0 | b.0, a.1 && b.1))
    } else {
        rows(film, rect)
            .map(scan)
            .fold((0, true), |a, b| (a.0 | b.0, a.1 && b.1))
    };
    let sum_bytes = ((64 - max.leading_zeros()).div_ceil(8)).max(1) as u8;
    let n = sum_bytes as usize;
    let row_bytes = rect.width as usize * 3 * n;
    let mut sums = vec![0u8; rect.area() * 3 * n];
    let write_row = |(out, r): (&mut [u8], std::ops::Range<usize>)| match n {
        1 => pack_row::<1>(out, &film.sums[r]),
        2 => pack_row::<2>(out, &film.sums[r]),
        3 => pack_row::<3>(out, &film.sums[r]),
        4 => pack_row::<4>(out, &film.sums[r]),
        5 => pack_row::<5>(out, &film.sums[r]),
        6 => pack_row::<6>(out, &film.sums[r]),
        7 => pack_row::<7>(out, &film.sums[r]),
        _ => pack_row::<8>(out, &film.sums[r]),
    };
    if row_bytes > 0 {
        if parallel {
            let rows: Vec<_> = rows(film, rect).collect();
            sums.par_chunks_mut(row_bytes).zip(rows).for_each(write_row);
        } else {
            sums.chunks_mut(row_bytes)
                .zip(rows(film, rect))
                .for_each(write_row);
        }
    }
    let uniform_count = if uniform { count.or(Some(0)) } else { None };
    let mut counts = Vec::new();
    if uniform_count.is_none() {
        counts.reserve(rect.area() * COUNT_BYTES);
        for r in rows(film, rect) {
            for c in &film.counts[r] {
                counts.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    Packed {
        sum_bytes,
        uniform_count,
        sums: sums.into(),
        counts: counts.into(),
    }
}

/// A row of sums as their low `N` bytes each (see [`unpack_sums`]).
fn pack_row<const N: usize>(out: &mut [u8], sums: &[[u64; 3]]) {
    for (o, s) in out.chunks_exact_mut(3 * N).zip(sums) {
        for (c, v) in s.iter().enumerate() {
            o[c * N..(c + 1) * N].copy_from_slice(&v.to_le_bytes()[..N]);
        }
    }
}

/// A whole film in the compact layout.
pub fn pack(film: &Film) -> Packed {
    pack_part(film, film.rect)
}

/// Sums of `N` bytes each, three a pixel, as `u64`s. The width is a
/// constant so that each value is a fixed-size load, not a `memcpy` of a
/// variable length (a GPU result is millions of them).
fn unpack_sums<const N: usize>(sums: &[u8]) -> Vec<[u64; 3]> {
    let value = |b: &[u8]| {
        let mut le = [0u8; 8];
        le[..N].copy_from_slice(&b[..N]);
        u64::from_le_bytes(le)
    };
    let pixel = |p: &[u8]| [value(p), value(&p[N..]), value(&p[2 * N..])];
    if sums.len() / (3 * N) >= PARALLEL_PIXELS {
        sums.par_chunks_exact(3 * N).map(pixel).collect()
    } else {
        sums.chunks_exact(3 * N).map(pixel).collect()
    }
}

/// Rebuilds a film from fields in `encoding`, checking their sizes against `rect`.
pub fn unpack_with(
    rect: Rect,
    encoding: Encoding,
    sums: &[u8],
    counts: &[u8],
    rays: RayCounts,
    nonfinite: u64,
) -> Result<Film, FilmCodecError> {
    let n = encoding.sum_bytes as usize;
    if !(1..=8).contains(&n) {
        return Err(FilmCodecError::SumBytes(encoding.sum_bytes.into()));
    }
    let area = rect.area();
    let (Some(sum_bytes), Some(count_bytes)) = (encoding.sums_len(area), encoding.counts_len(area))
    else {
        return Err(FilmCodecError::TooLarge {
            width: rect.width,
            height: rect.height,
        });
    };
    if sums.len() != sum_bytes {
        return Err(FilmCodecError::SumsSize {
            got: sums.len(),
            expected: sum_bytes,
            width: rect.width,
            height: rect.height,
        });
    }
    if counts.len() != count_bytes {
        return Err(FilmCodecError::CountsSize {
            got: counts.len(),
            expected: count_bytes,
            width: rect.width,
            height: rect.height,
        });
    }
    let sums = match n {
        1 => unpack_sums::<1>(sums),
        2 => unpack_sums::<2>(sums),
        3 => unpack_sums::<3>(sums),
        4 => unpack_sums::<4>(sums),
        5 => unpack_sums::<5>(sums),
        6 => unpack_sums::<6>(sums),
        7 => unpack_sums::<7>(sums),
        _ => unpack_sums::<8>(sums),
    };
    let counts = match encoding.uniform_count {
        Some(c) => vec![c; area],
        None => counts
            .chunks_exact(COUNT_BYTES)
            .map(|c| u32::from_le_bytes(c.try_into().expect("chunk of 4")))
            .collect(),
    };
    Ok(Film {
        rect,
        sums,
        counts,
        rays,
        nonfinite,
        squares: None,
        runs: Vec::new(),
    })
}

/// The sums of squares of an adaptive film's part inside `rect`, each as
/// its low `square_bytes` little-endian bytes (the fewest that hold the
/// largest, 1 to 16): `None` for a film without squares. Uniform films
/// never carry this section, so their bytes are as before.
pub fn pack_squares_part(film: &Film, rect: Rect) -> Option<(u8, Vec<u8>)> {
    let squares = film.squares.as_ref()?;
    let mut max = 0u128;
    for r in rows(film, rect) {
        for s in &squares[r] {
            max |= s[0] | s[1] | s[2];
        }
    }
    let n = ((128 - max.leading_zeros()).div_ceil(8)).max(1) as usize;
    let mut out = Vec::with_capacity(rect.area() * 3 * n);
    for r in rows(film, rect) {
        for s in &squares[r] {
            for v in s {
                out.extend_from_slice(&v.to_le_bytes()[..n]);
            }
        }
    }
    Some((n as u8, out))
}

/// Attaches sums of squares packed by [`pack_squares_part`] to a film
/// decoded from the same part, checking their size.
pub fn unpack_squares(
    film: &mut Film,
    square_bytes: u8,
    bytes: &[u8],
) -> Result<(), FilmCodecError> {
    let n = square_bytes as usize;
    if !(1..=16).contains(&n) {
        return Err(FilmCodecError::SquareBytes(square_bytes.into()));
    }
    let expected = film
        .rect
        .area()
        .checked_mul(3 * n)
        .ok_or(FilmCodecError::TooLarge {
            width: film.rect.width,
            height: film.rect.height,
        })?;
    if bytes.len() != expected {
        return Err(FilmCodecError::SquaresSize {
            got: bytes.len(),
            expected,
            square_bytes,
            width: film.rect.width,
            height: film.rect.height,
        });
    }
    let value = |b: &[u8]| {
        let mut le = [0u8; 16];
        le[..n].copy_from_slice(b);
        u128::from_le_bytes(le)
    };
    film.squares = Some(
        bytes
            .chunks_exact(3 * n)
            .map(|p| [value(&p[..n]), value(&p[n..2 * n]), value(&p[2 * n..])])
            .collect(),
    );
    Ok(())
}

pub fn pack_sums(film: &Film) -> Vec<u8> {
    let mut out = Vec::with_capacity(film.sums.len() * SUM_BYTES);
    for s in &film.sums {
        for c in s {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

pub fn pack_counts(film: &Film) -> Vec<u8> {
    let mut out = Vec::with_capacity(film.counts.len() * COUNT_BYTES);
    for c in &film.counts {
        out.extend_from_slice(&c.to_le_bytes());
    }
    out
}

/// Rebuilds a film from fields in the original layout, checking their sizes against `rect`.
pub fn unpack(
    rect: Rect,
    sums: &[u8],
    counts: &[u8],
    rays: RayCounts,
    nonfinite: u64,
) -> Result<Film, FilmCodecError> {
    unpack_with(rect, Encoding::ORIGINAL, sums, counts, rays, nonfinite)
}

/// Rebuilds a film from its packed fields, wherever they came from (a
/// result on the wire, a film in the store's container): sums and counts
/// in `encoding`, and an adaptive film's sums of squares (`square_bytes`
/// wide, as the wire's `square_bytes` field holds it), sizes checked
/// against `rect`.
pub fn unpack_film(
    rect: Rect,
    encoding: Encoding,
    sums: &[u8],
    counts: &[u8],
    squares: Option<(u32, &[u8])>,
    rays: RayCounts,
    nonfinite: u64,
) -> Result<Film, FilmCodecError> {
    let mut film = unpack_with(rect, encoding, sums, counts, rays, nonfinite)?;
    if let Some((square_bytes, bytes)) = squares {
        let n =
            u8::try_from(square_bytes).map_err(|_| FilmCodecError::SquareBytes(square_bytes))?;
        unpack_squares(&mut film, n, bytes)?;
    }
    Ok(film)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Films large enough to pack and unpack in parallel give the bytes a
    /// plain loop gives, for a part and for the whole, and round-trip.
    #[test]
    fn large_films_pack_in_parallel_to_the_same_bytes() {
        let rect = Rect::new(0, 0, 700, 400);
        let mut f = Film::new(rect);
        for (i, (s, c)) in f.sums.iter_mut().zip(&mut f.counts).enumerate() {
            let i = i as u64;
            *s = [i * 977 % 100_003, (i * 31) << 8, i ^ 0x5a5a];
            *c = 64;
        }
        for part in [rect, Rect::new(5, 3, 690, 390)] {
            assert!(part.area() >= PARALLEL_PIXELS);
            let p = pack_part(&f, part);
            assert_eq!((p.sum_bytes, p.uniform_count), (4, Some(64)));
            let (mut expected, mut cropped) = (vec![], vec![]);
            for y in part.y..part.y + part.height {
                for x in part.x..part.x + part.width {
                    let s = f.sums[(y * rect.width + x) as usize];
                    cropped.push(s);
                    for v in s {
                        expected.extend_from_slice(&v.to_le_bytes()[..4]);
                    }
                }
            }
            assert!(p.sums == expected, "sums bytes differ");
            let back = unpack_with(part, p.encoding(), &p.sums, &p.counts, f.rays, 0).unwrap();
            assert!(back.sums == cropped && back.counts.iter().all(|&c| c == 64));
        }
        // One pixel with another count: the counts field is sent.
        f.counts[123_456] = 63;
        let p = pack(&f);
        assert_eq!(p.uniform_count, None);
        let back = unpack_with(rect, p.encoding(), &p.sums, &p.counts, f.rays, 0).unwrap();
        assert!(back.counts == f.counts && back.sums == f.sums);
    }

    #[test]
    fn round_trip_and_size_checks() {
        let rect = Rect::new(2, 3, 3, 2);
        let mut f = Film::new(rect);
        f.sums[4] = [1, u64::MAX, 1 << 40];
        f.counts[5] = 7;
        f.rays.primary = 9;
        let (s, c) = (pack_sums(&f), pack_counts(&f));
        assert_eq!(unpack(rect, &s, &c, f.rays, 0), Ok(f));
        assert_eq!(
            unpack(rect, &s[1..], &c, RayCounts::default(), 0),
            Err(FilmCodecError::SumsSize {
                got: 143,
                expected: 144,
                width: 3,
                height: 2
            })
        );
        assert!(matches!(
            unpack(rect, &s, &c[..20], RayCounts::default(), 0),
            Err(FilmCodecError::CountsSize { .. })
        ));
    }

    #[test]
    fn every_sum_width_round_trips_at_its_limits() {
        // Each width from 1 to 8 bytes (a code path each), serial and
        // parallel, with the largest value of that width in every channel.
        for n in 1..=8u32 {
            let max = if n == 8 {
                u64::MAX
            } else {
                (1u64 << (8 * n)) - 1
            };
            for (w, h) in [(7, 3), (1024, 300)] {
                let rect = Rect::new(0, 0, w, h);
                let mut f = Film::new(rect);
                for (i, s) in f.sums.iter_mut().enumerate() {
                    let i = i as u64;
                    *s = [
                        max,
                        max - (i % 251),
                        i.wrapping_mul(0x9e37_79b9_7f4a_7c15) & max,
                    ];
                }
                f.counts.fill(3);
                let p = pack(&f);
                assert_eq!(u32::from(p.sum_bytes), n, "{w}x{h}");
                assert_eq!(p.sums.len(), rect.area() * 3 * n as usize);
                let g = unpack_with(rect, p.encoding(), &p.sums, &p.counts, f.rays, 0).unwrap();
                assert!(g == f, "width {n}, {w}x{h}");
            }
        }
    }

    #[test]
    fn the_compact_layout_is_exact_and_small() {
        let rect = Rect::new(10, 20, 5, 4);
        let mut f = Film::new(rect);
        for (i, s) in f.sums.iter_mut().enumerate() {
            *s = [i as u64, (i as u64) << 30, 3 << 36];
        }
        f.counts.fill(64);
        f.rays.shadow = 5;
        let p = pack(&f);
        // 3 << 36 needs 38 bits: 5 bytes a sum; one count for all pixels.
        assert_eq!((p.sum_bytes, p.uniform_count), (5, Some(64)));
        assert_eq!((p.sums.len(), p.counts.len()), (20 * 15, 0));
        assert_eq!(
            unpack_with(rect, p.encoding(), &p.sums, &p.counts, f.rays, 0),
            Ok(f.clone())
        );
        // Counts that differ are kept per pixel; a crop packs only its pixels.
        f.counts[3] = 1;
        let part = Rect::new(11, 21, 3, 2);
        let p = pack_part(&f, part);
        assert_eq!(p.uniform_count, Some(64));
        let q = pack(&f);
        assert_eq!((q.uniform_count, q.counts.len()), (None, 80));
        assert_eq!(
            unpack_with(rect, q.encoding(), &q.sums, &q.counts, f.rays, 0),
            Ok(f.clone())
        );
        let crop = unpack_with(
            part,
            p.encoding(),
            &p.sums,
            &p.counts,
            RayCounts::default(),
            0,
        )
        .unwrap();
        assert_eq!(crop.sums[0], f.sums[6]);
        assert_eq!(crop.sums[5], f.sums[13]);
        // An empty film's sums take one byte each.
        let z = pack(&Film::new(rect));
        assert_eq!((z.sum_bytes, z.uniform_count), (1, Some(0)));
        assert_eq!(
            unpack_with(
                rect,
                Encoding {
                    sum_bytes: 9,
                    uniform_count: None
                },
                &[],
                &[],
                RayCounts::default(),
                0
            ),
            Err(FilmCodecError::SumBytes(9))
        );
    }

    #[test]
    fn squares_round_trip_exactly_and_only_for_adaptive_films() {
        let rect = Rect::new(8, 0, 3, 2);
        assert_eq!(pack_squares_part(&Film::new(rect), rect), None);
        let mut f = Film::with_squares(rect);
        f.sums[1] = [5, 6, 7];
        f.counts[1] = 2;
        f.squares.as_mut().unwrap()[1] = [1 << 100, 3, 0];
        f.squares.as_mut().unwrap()[4] = [u128::MAX >> 20, 0, 9];
        let part = Rect::new(9, 0, 2, 2);
        let (n, bytes) = pack_squares_part(&f, rect).unwrap();
        assert_eq!(n, 14);
        let p = pack(&f);
        let mut g = unpack_with(rect, p.encoding(), &p.sums, &p.counts, f.rays, 0).unwrap();
        unpack_squares(&mut g, n, &bytes).unwrap();
        assert_eq!(g, f);
        // A part: its own pixels only; the smallest width that holds them.
        let (n, bytes) = pack_squares_part(&f, part).unwrap();
        let mut h = Film::new(part);
        unpack_squares(&mut h, n, &bytes).unwrap();
        assert_eq!(h.squares.unwrap()[0], [1 << 100, 3, 0]);
        assert_eq!(
            unpack_squares(&mut g, n, &bytes[1..]),
            Err(FilmCodecError::SquaresSize {
                got: bytes.len() - 1,
                expected: 6 * 3 * n as usize,
                square_bytes: n,
                width: 3,
                height: 2
            })
        );
        assert_eq!(
            unpack_squares(&mut g, 17, &[]),
            Err(FilmCodecError::SquareBytes(17))
        );
    }

    /// Found by fuzz/fuzz_targets/film_codec.rs: the expected size of a
    /// 2^32-1 square rect's sums overflowed (a panic in checked builds).
    #[test]
    fn rects_too_large_for_memory_are_errors_not_overflows() {
        let rect = Rect::new(0, 0, u32::MAX, u32::MAX);
        let e = unpack(rect, &[0; 24], &[0; 4], RayCounts::default(), 0).unwrap_err();
        assert_eq!(
            e.to_string(),
            "a 4294967295x4294967295 rect is too large for a film (24 bytes a pixel)"
        );
    }
}
