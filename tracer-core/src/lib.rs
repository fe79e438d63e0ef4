//! Tessera's tracer core: the scene format, geometry, the Whitted shading
//! model of the 2015 thesis, deterministic sampling, and the renderers.
//!
//! Data flow: [`scene::SceneDesc`] (parsed, validated, `f64`) ->
//! [`render::PreparedFrame`] (render-ready [`world::World`] for one frame
//! and precision, camera-relative) -> a renderer renders any
//! [`film::WorkRegion`] (a [`film::Rect`] of a frame over a
//! [`film::SampleRange`]) into a [`film::Film`] of fixed-point
//! per-pixel sums -> films add up exactly -> [`film::Film::resolve`].
//!
//! ```
//! use tracer_core::{film::{Rect, SampleRange, WorkRegion}, render::{CpuRenderer, PreparedFrame, Precision}, scene::SceneDesc};
//! let scene = SceneDesc::parse(r#"
//!     [render]
//!     width = 8
//!     height = 6
//!     [camera]
//!     position = [0, 1, -6]
//!     look_at = [0, 1, 0]
//!     [materials.red]
//!     diffuse = [1, 0, 0]
//!     [[lights]]
//!     position = [0, 5, -5]
//!     [[objects]]
//!     type = "sphere"
//!     center = [0, 1, 0]
//!     radius = 1
//!     material = "red"
//! "#, "doc.toml").unwrap();
//! let frame = PreparedFrame::build(&scene, &scene.render, 0, Precision::F32).unwrap();
//! let film = CpuRenderer::new(Some(1)).unwrap()
//!     .render(&frame, WorkRegion::new(0, Rect::full(8, 6), SampleRange::all(4)), &|_| {}).unwrap();
//! let image = film.resolve();
//! assert!(image[2 * 8 + 3][0] > 0.5); // the sphere in the middle is lit red
//! assert_eq!(image[0], [0.0; 3]);       // the corner sees the black background
//! ```

pub mod accel;
pub mod adaptive;
pub mod assets;
pub mod bsdf;
pub mod bvh;
pub mod distributed;
pub mod emitters;
pub mod environment;
pub mod film;
pub mod geometry;
pub mod light;
pub mod material;
pub mod math;
pub mod mesh;
pub mod render;
pub mod sampling;
pub mod scene;
pub mod simd;
pub mod texture;
pub mod triangle;
pub mod world;
