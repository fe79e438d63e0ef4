//! Films on the wire: fixed-point sums as packed little-endian `u64`
//! (R, G, B per pixel) and sample counts as packed little-endian `u32`.

use tracer_core::film::{Film, RayCounts, Rect};

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

/// Rebuilds a film from packed fields, checking their sizes against `rect`.
pub fn unpack(
    rect: Rect,
    sums: &[u8],
    counts: &[u8],
    rays: RayCounts,
    nonfinite: u64,
) -> Result<Film, FilmCodecError> {
    let area = rect.area();
    // A rect from the wire can ask for more bytes than a usize holds: an
    // overflow (or, unchecked, a wrapped size a short field could match).
    let (Some(sum_bytes), Some(count_bytes)) =
        (area.checked_mul(SUM_BYTES), area.checked_mul(COUNT_BYTES))
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
    let u64_at = |b: &[u8]| u64::from_le_bytes(b.try_into().expect("chunk of 8"));
    let sums = sums
        .chunks_exact(SUM_BYTES)
        .map(|p| [u64_at(&p[0..8]), u64_at(&p[8..16]), u64_at(&p[16..24])])
        .collect();
    let counts = counts
        .chunks_exact(COUNT_BYTES)
        .map(|c| u32::from_le_bytes(c.try_into().expect("chunk of 4")))
        .collect();
    Ok(Film {
        rect,
        sums,
        counts,
        rays,
        nonfinite,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
