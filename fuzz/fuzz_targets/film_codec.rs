//! `film_codec::unpack` (films arriving from workers and from the store)
//! on arbitrary rects and field contents; what it accepts must pack back to
//! the same bytes. The first 17 bytes are a mode and the rect (x, y, width,
//! height as little-endian u32; with mode bit 0 set, width and height are
//! taken modulo 64 so that sizes match often); the rest is split by its
//! first u16 into the sums and counts fields.
#![no_main]

use libfuzzer_sys::fuzz_target;
use tessera_proto::film_codec::{pack_counts, pack_sums, unpack};
use tracer_core::film::{RayCounts, Rect};

fuzz_target!(|data: &[u8]| {
    tessera_fuzz::init();
    if data.len() < 19 {
        return;
    }
    let u32_at = |i: usize| u32::from_le_bytes(data[i..i + 4].try_into().unwrap());
    let mode = data[0];
    let (mut width, mut height) = (u32_at(9), u32_at(13));
    if mode & 1 == 1 {
        width %= 64;
        height %= 64;
    }
    let rect = Rect::new(u32_at(1), u32_at(5), width, height);
    let split = u16::from_le_bytes([data[17], data[18]]) as usize;
    let rest = &data[19..];
    let (sums, counts) = rest.split_at(split.min(rest.len()));
    let rays = RayCounts {
        primary: u64::MAX,
        shadow: rest.len() as u64,
        ..Default::default()
    };
    if let Ok(film) = unpack(rect, sums, counts, rays, 7) {
        assert_eq!(film.rect, rect);
        assert_eq!(film.sums.len(), rect.area());
        assert_eq!(film.counts.len(), rect.area());
        assert_eq!(pack_sums(&film), sums);
        assert_eq!(pack_counts(&film), counts);
    }
});
