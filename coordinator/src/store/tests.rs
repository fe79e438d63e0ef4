//! The store's tests: records of earlier releases, films in files, outages.

use std::time::{Duration, Instant};

use tessera_proto::film_codec;
use tracer_core::adaptive::AdaptiveSettings;
use tracer_core::film::{RayCounts, Rect};
use tracer_core::scene::RenderSettings;

use super::schema::SettingsRec;
use super::*;
use tessera_proto::film_codec::{ADAPTIVE_MAGIC, COMPACT_MAGIC};
use tracer_core::sampling::Sampler;

/// A job record as releases before `JobSpec` wrote it (with the
/// adaptive fields of issue 17), field for field.
const RECORD: &str = r#"{"id":"j0123456789","name":"glass","scene_name":"examples/glass.toml",
    "scene_sha256":"ab","assets":{"m.obj":"cd"},"width":320,"height":240,"samples":1024,
    "max_depth":6,"sampler":"progressive","first_frame":1,"last_frame":3,"priority":-2,
    "tile_size":64,"samples_per_unit":64,"max_attempts":3,"state":"Active","error":"",
    "submitted_unix_ms":1700000000000,"finished_unix_ms":0,"output_dir":"/data/outputs/j0123456789",
    "target_error":0.01,"min_samples":16,"max_samples":1024,"relative_error":0.0}"#;

#[test]
fn job_records_of_earlier_releases_still_load_and_keep_their_shape() {
    let rec = JobRecord::from_json(RECORD.as_bytes()).unwrap();
    assert_eq!(
        rec.settings,
        RenderSettings {
            width: 320,
            height: 240,
            samples: 1024,
            max_depth: 6,
            sampler: Sampler::Progressive,
            integrator: Default::default(),
        }
    );
    assert_eq!((rec.first_frame, rec.last_frame, rec.priority), (1, 3, -2));
    assert_eq!(rec.state, JobStateRec::Active);
    assert_eq!(
        rec.adaptive,
        Some(AdaptiveSettings {
            target_error: 0.01,
            relative_error: 0.0,
            min_samples: 16,
            max_samples: 1024,
            mode: tracer_core::adaptive::AdaptiveMode::Pixel,
        })
    );
    // Written back, it is the same JSON object: same names, the
    // sampler still a string.
    let old: serde_json::Value = serde_json::from_str(RECORD).unwrap();
    assert_eq!(
        serde_json::from_slice::<serde_json::Value>(&rec.to_json()).unwrap(),
        old
    );

    // Before adaptive sampling: no adaptive fields, a "grid" or
    // "jittered" sampler; a uniform job.
    let mut before: serde_json::Map<String, serde_json::Value> =
        serde_json::from_str(RECORD).unwrap();
    for k in [
        "target_error",
        "min_samples",
        "max_samples",
        "relative_error",
    ] {
        before.remove(k);
    }
    before.insert("sampler".into(), "jittered".into());
    let rec = JobRecord::from_json(&serde_json::to_vec(&before).unwrap()).unwrap();
    assert_eq!(rec.settings.sampler, Sampler::Jittered);
    assert_eq!(rec.adaptive, None);
    for s in ["grid", "jittered", "progressive"] {
        let v = serde_json::to_value(SettingsRec::from(RenderSettings {
            sampler: s.parse().unwrap(),
            ..rec.settings
        }))
        .unwrap();
        assert_eq!(v["sampler"], s);
    }
}

/// Records are versioned: version 1 (every record so far) is written
/// without the key and read with or without it; a newer version is
/// refused by name, not misread.
#[test]
fn job_records_carry_their_version_and_a_newer_one_is_refused() {
    let rec = JobRecord::from_json(RECORD.as_bytes()).unwrap();
    assert!(
        !String::from_utf8(rec.to_json())
            .unwrap()
            .contains("version")
    );
    let mut v1: serde_json::Value = serde_json::from_str(RECORD).unwrap();
    v1["version"] = 1.into();
    assert_eq!(
        JobRecord::from_json(&serde_json::to_vec(&v1).unwrap()),
        Ok(rec)
    );
    v1["version"] = 2.into();
    assert_eq!(
        JobRecord::from_json(&serde_json::to_vec(&v1).unwrap()),
        Err("job record version 2 is newer than the 1 this release reads".into())
    );
}

/// A record this release cannot read (a sampler from a newer release)
/// is left out; the other jobs still load.
#[test]
fn an_unreadable_job_record_does_not_stop_the_others_loading() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(&dir.path().join("t.redb")).unwrap();
    let good = JobRecord::from_json(RECORD.as_bytes()).unwrap();
    let mut newer: serde_json::Value = serde_json::from_str(RECORD).unwrap();
    newer["id"] = "jnewer".into();
    newer["sampler"] = "blue-noise".into();
    let db = store.db().unwrap();
    let w = db.begin_write().unwrap();
    {
        let mut t = w.open_table(JOBS).unwrap();
        let newer = serde_json::to_vec(&newer).unwrap();
        t.insert("jnewer", newer.as_slice()).unwrap();
        let good = good.to_json();
        t.insert("j0123456789", good.as_slice()).unwrap();
    }
    w.commit().unwrap();
    let snap = store.load().unwrap();
    let ids: Vec<&str> = snap.jobs.iter().map(|(r, _)| r.id.as_str()).collect();
    assert_eq!(ids, ["j0123456789"]);
}

fn film() -> Film {
    let mut film = Film::new(Rect::new(8, 4, 5, 3));
    for (i, (s, c)) in film.sums.iter_mut().zip(film.counts.iter_mut()).enumerate() {
        *s = [i as u64, (i as u64) << 40, u64::MAX - i as u64];
        *c = 7 + i as u32;
    }
    film.rays = RayCounts {
        primary: 1,
        shadow: 2,
        reflection: 3,
        refraction: 4,
    };
    film.nonfinite = 9;
    film
}

#[test]
fn adaptive_films_keep_their_squares_in_the_store() {
    let mut f = film();
    f.squares = Some((0..15u128).map(|i| [i << 90, i, 0]).collect());
    let b = encode_film(&f);
    assert!(b.starts_with(&ADAPTIVE_MAGIC));
    assert_eq!(decode_film(&b), Ok(f.clone()));
    // A uniform film's bytes do not change.
    assert!(encode_film(&film()).starts_with(&COMPACT_MAGIC));
    assert!(decode_film(&b[..b.len() - 1]).is_err());
}

fn block_on<F: std::future::Future>(f: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(f)
}

/// The store at `path` once its previous handle's writer let go of it.
fn reopen(path: &Path) -> Store {
    let start = Instant::now();
    loop {
        match Store::open(path) {
            Ok(s) => return s,
            Err(e) if start.elapsed() < Duration::from_secs(5) => {
                let _ = e;
                std::thread::sleep(Duration::from_millis(10));
            }
            Err(e) => panic!("{e}"),
        }
    }
}

fn film_files_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    names
}

fn accept(job: &str, first_unit: u32, film: StoredFilm) -> Op {
    Op::AcceptUnits {
        job: job.into(),
        first_unit,
        film,
        units: 1,
        rays: [1, 2, 3, 4],
    }
}

/// A large film lives in a file of its own: it loads after a restart,
/// its file goes with its frame's record, and a file no record names
/// (a result whose commit was lost) is removed at open.
#[test]
fn a_large_film_is_kept_in_a_file_until_its_frame_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.redb");
    let films_dir = dir.path().join("t.films");
    let store = Store::open(&path).unwrap();
    store.set_min_file_film(1);
    let stored = store
        .store_film("j1", 0, EncodedFilm::of_film(&film()))
        .unwrap();
    assert!(matches!(stored, StoredFilm::File(_)), "{stored:?}");
    let small = Store::open(&dir.path().join("u.redb")).unwrap();
    assert!(
        matches!(
            small.store_film("j1", 0, EncodedFilm::of_film(&film())),
            Ok(StoredFilm::Inline(_))
        ),
        "below a megabyte a film stays in the database"
    );
    block_on(store.write(vec![accept("j1", 0, stored)])).unwrap();
    block_on(store.sync()).unwrap();
    let [kept] = &film_files_in(&films_dir)[..] else {
        panic!("{:?}", film_files_in(&films_dir));
    };
    let kept = kept.clone();
    std::fs::write(films_dir.join("j1-1-00.film"), b"never recorded").unwrap();
    drop(store);

    let store = reopen(&path);
    assert_eq!(film_files_in(&films_dir), [kept]);
    let snap = store.load().unwrap();
    assert_eq!(snap.unit_films["j1"], [(0, film())]);
    block_on(store.write(vec![Op::FrameWritten {
        job: "j1".into(),
        frame: 0,
        file: "frame_0000.png".into(),
        units: 0..1,
    }]))
    .unwrap();
    assert!(store.load().unwrap().unit_films.is_empty());
    // (Removed on a thread of its own, after the commit.)
    let start = Instant::now();
    while !film_files_in(&films_dir).is_empty() {
        assert!(start.elapsed() < Duration::from_secs(5), "file not removed");
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// A film that cannot be written (here its directory is a file) is a
/// storage outage like a failed commit: refused with the path named,
/// nothing left behind, and over once writes succeed again.
#[test]
fn a_film_that_cannot_be_written_is_an_outage_that_heals() {
    let dir = tempfile::tempdir().unwrap();
    let films_dir = dir.path().join("t.films");
    let store = Store::open(&dir.path().join("t.redb")).unwrap();
    store.set_min_file_film(1);
    std::fs::remove_dir(&films_dir).unwrap();
    std::fs::write(&films_dir, b"in the way").unwrap();
    let e = store
        .store_film("j1", 0, EncodedFilm::of_film(&film()))
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with(&format!(
            "cannot write the database: cannot write the film {}/j1-0-",
            films_dir.display()
        )),
        "{e}"
    );
    assert!(!store.health.ok());
    std::fs::remove_file(&films_dir).unwrap();
    std::fs::create_dir(&films_dir).unwrap();
    let start = Instant::now();
    while !store.health.ok() {
        assert!(start.elapsed() < Duration::from_secs(10), "never healed");
        std::thread::sleep(Duration::from_millis(20));
    }
    let stored = store
        .store_film("j1", 0, EncodedFilm::of_film(&film()))
        .unwrap();
    block_on(store.write(vec![accept("j1", 0, stored)])).unwrap();
    assert_eq!(store.load().unwrap().unit_films["j1"], [(0, film())]);
    assert_eq!(film_files_in(&films_dir).len(), 1);
}

#[test]
fn a_film_part_encodes_as_the_cropped_film() {
    let film = film();
    assert_eq!(decode_film(&encode_film(&film)), Ok(film.clone()));
    let part = Rect::new(9, 5, 3, 2);
    let mut cropped = Film::new(part);
    for row in 0..2 {
        for col in 0..3 {
            let src = ((row + 1) * 5 + col + 1) as usize;
            cropped.sums[(row * 3 + col) as usize] = film.sums[src];
            cropped.counts[(row * 3 + col) as usize] = film.counts[src];
        }
    }
    let got = decode_film(&encode_film_part(&film, part, RayCounts::default(), 0)).unwrap();
    assert_eq!(got, cropped);
}

/// Films stored by earlier versions (56-byte header, 28 bytes a pixel)
/// still decode; damaged ones are errors, never panics.
#[test]
fn films_in_the_original_layout_still_decode() {
    let film = film();
    let mut old = Vec::new();
    for v in [8u32, 4, 5, 3] {
        old.extend_from_slice(&v.to_le_bytes());
    }
    for v in [1u64, 2, 3, 4, 9] {
        old.extend_from_slice(&v.to_le_bytes());
    }
    old.extend_from_slice(&film_codec::pack_sums(&film));
    old.extend_from_slice(&film_codec::pack_counts(&film));
    assert_eq!(decode_film(&old), Ok(film.clone()));
    let new = encode_film(&film);
    for cut in [0, 10, 60, 66, new.len() - 1] {
        assert!(decode_film(&new[..cut]).is_err(), "cut at {cut}");
    }
    let mut bad = new.clone();
    bad[60] = 9;
    assert_eq!(
        decode_film(&bad),
        Err("sum_bytes must be 1 to 8, got 9".into())
    );
}
