//! Render-ready state of distributed ray tracing (Cook, Porter and
//! Carpenter 1984): area lights, glossy reflection and translucency, depth
//! of field and motion blur. A [`World`] carries it only when its scene uses
//! one of these effects (`World::dist`); every other scene is built and
//! rendered exactly as before, bit for bit, and pays nothing.
//!
//! Motion is linear within a frame (keyframes lie on whole frames), so an
//! object's position at shutter fraction `tau` is its position at the
//! shutter's opening plus `tau` times its displacement over the shutter.
//! Moving spheres and meshes are kept out of the static arrays and the
//! static tree: each has a box bounding its sweep over the shutter, tested
//! first; a moving mesh keeps its own tree, built at the shutter's opening,
//! which the ray enters translated by the mesh's displacement.

use crate::emitters::TriEmitter;
use crate::geometry::Sphere;
use crate::math::{Ray, Real, Vector3};
use crate::scene::{CameraPose, LightShape, SceneDesc};
use crate::world::World;

pub use crate::light::{Light, LightGeom};

/// Depth of field: the thin lens.
#[derive(Clone, Copy, Debug)]
pub struct Lens<R: Real> {
    pub aperture: R,
    /// `None`: |look_at - position| of the sample's pose.
    pub focus_distance: Option<R>,
}

/// A camera that moves during the shutter: the pose at shutter fraction
/// tau is the opening pose plus tau times the change (camera-relative).
#[derive(Clone, Copy, Debug)]
pub struct CameraMotion<R: Real> {
    pub delta_position: R::V3,
    pub look_at: R::V3,
    pub delta_look_at: R::V3,
    pub fov_y: f64,
    pub delta_fov_y: f64,
    pub up: R::V3,
    pub aspect: R,
}

/// The camera frame of one sample: its origin, unit forward, right and up
/// vectors, the scaled vectors of [`crate::world::Camera`], and the focus.
#[derive(Clone, Copy, Debug)]
pub struct CameraFrame<R: Real> {
    pub origin: R::V3,
    pub camera: crate::world::Camera<R>,
    pub unit_right: R::V3,
    pub unit_up: R::V3,
    /// |look_at - position| of this pose.
    pub look_distance: R,
}

#[derive(Clone, Debug)]
pub struct MovingSphere<R: Real> {
    /// At the shutter's opening.
    pub sphere: Sphere<R>,
    pub delta: R::V3,
    /// Box of the sweep over the shutter.
    pub lo: R::V3,
    pub hi: R::V3,
}

impl<R: Real> MovingSphere<R> {
    #[inline]
    pub fn at(&self, tau: R) -> Sphere<R> {
        Sphere {
            center: self.sphere.center + self.delta * tau,
            ..self.sphere
        }
    }
}

#[derive(Clone, Debug)]
pub struct MovingMesh<R: Real> {
    /// The mesh alone at the shutter's opening, with its own tree.
    pub world: World<R>,
    pub delta: R::V3,
    pub lo: R::V3,
    pub hi: R::V3,
}

/// Whether `ray` meets the box [lo, hi] before `t_max` (slab test).
#[inline]
pub fn ray_meets_box<R: Real>(ray: &Ray<R>, lo: R::V3, hi: R::V3, t_max: R) -> bool {
    let (o, d) = (ray.origin.to_array(), ray.dir.to_array());
    let (lo, hi) = (lo.to_array(), hi.to_array());
    let (mut t0, mut t1) = (0.0f64, t_max.to_f64());
    for k in 0..3 {
        let inv = 1.0 / d[k];
        let (a, b) = ((lo[k] - o[k]) * inv, (hi[k] - o[k]) * inv);
        let (a, b) = if a < b { (a, b) } else { (b, a) };
        // NaN (a ray in the slab's plane) keeps the interval.
        if a > t0 {
            t0 = a;
        }
        if b < t1 {
            t1 = b;
        }
        // Widened a little: the box only culls.
        if t0 > t1 * (1.0 + 1e-6) + 1e-9 {
            return false;
        }
    }
    true
}

/// Which effects are on; each off means its code is not run at all.
#[derive(Clone, Debug)]
pub struct Distributed<R: Real> {
    /// Every light, in file order (point lights too, so that terms add in
    /// the file's order).
    pub lights: Vec<Light<R>>,
    /// Whether any light is an area light.
    pub area_lights: bool,
    /// Whether any material has a gloss or translucency cone.
    pub cones: bool,
    pub lens: Option<Lens<R>>,
    pub camera_motion: Option<CameraMotion<R>>,
    pub moving_spheres: Vec<MovingSphere<R>>,
    pub moving_meshes: Vec<MovingMesh<R>>,
    /// Whether a sample's time is drawn (something moves during the shutter).
    pub blur: bool,
    /// Camera at the shutter's opening: unit right and up vectors and
    /// |look_at - position|.
    pub unit_right: R::V3,
    pub unit_up: R::V3,
    pub look_distance: R,
    /// The path integrator's state, when the render integrates paths.
    pub path: Option<PathScene<R>>,
}

/// What the path integrator needs beyond the lights: the environment and
/// the power-proportional light selection, over the lights, then the
/// environment image where there is one, then the emissive triangles
/// (`crate::emitters`).
#[derive(Clone, Debug)]
pub struct PathScene<R: Real> {
    /// The uniform environment (BSDF-sampled only).
    pub environment: R::V3,
    /// The environment image, light-sampled as the selection's entry
    /// right after the lights (`Self::env_index`).
    pub environment_map: Option<std::sync::Arc<crate::environment::EnvironmentMap>>,
    /// The image's selection probability (0 without one).
    pub env_prob: R,
    /// Running sums of the selection probabilities of the lights and then
    /// the emitters (the last is 1); empty when nothing emits.
    pub light_cdf: Vec<f64>,
    /// Each light's selection probability.
    pub light_prob: Vec<R>,
    /// The emissive triangles, selected after the lights.
    pub emitters: Vec<TriEmitter<R>>,
    /// Each material's probability of selecting a triangle of it per
    /// unit of its area (0: not light-sampled); empty without emitters.
    pub emit_density: Vec<R>,
}

impl<R: Real> PathScene<R> {
    /// `material_power`: per material, pi x mean emitted luminance
    /// (`emitters::material_power`), the emitters' power per unit area.
    /// `environment_map`: the image and the scene's radius (its power
    /// is r^2 times its integral: the flux through the scene's
    /// cross-section, over pi).
    pub fn new(
        lights: &[Light<R>],
        environment: R::V3,
        environment_map: Option<(std::sync::Arc<crate::environment::EnvironmentMap>, f64)>,
        emitters: Vec<TriEmitter<R>>,
        material_power: &[f64],
    ) -> Self {
        let env_power = environment_map.as_ref().map(|(m, r)| r * r * m.integral);
        let environment_map = environment_map.map(|(m, _)| m);
        let power: Vec<f64> = lights
            .iter()
            .map(|l| l.power())
            .chain(env_power)
            .chain(emitters.iter().map(|e| e.power))
            .collect();
        let total: f64 = power.iter().sum();
        if !(total > 0.0) {
            return PathScene {
                environment,
                environment_map,
                env_prob: R::ZERO,
                light_cdf: Vec::new(),
                light_prob: vec![R::ZERO; lights.len()],
                emitters: Vec::new(),
                emit_density: Vec::new(),
            };
        }
        let mut acc = 0.0;
        let light_cdf = power
            .iter()
            .map(|p| {
                acc += p / total;
                acc
            })
            .collect();
        let emit_density = if emitters.is_empty() {
            Vec::new()
        } else {
            material_power
                .iter()
                .map(|p| R::from_f64(p / total))
                .collect()
        };
        PathScene {
            environment,
            environment_map,
            env_prob: env_power.map_or(R::ZERO, |p| R::from_f64(p / total)),
            light_cdf,
            light_prob: power[..lights.len()]
                .iter()
                .map(|p| R::from_f64(p / total))
                .collect(),
            emitters,
            emit_density,
        }
    }

    /// The selection index of the environment image (after the lights),
    /// or `None` without one.
    pub fn env_index(&self) -> Option<usize> {
        self.environment_map.as_ref().map(|_| self.light_prob.len())
    }

    /// The selection index of the first emissive triangle.
    pub fn first_emitter(&self) -> usize {
        self.light_prob.len() + self.environment_map.is_some() as usize
    }

    /// The light for uniform `u`: the first whose running sum exceeds it.
    pub fn pick(&self, u: f32) -> usize {
        let u = u as f64;
        let i = self.light_cdf.partition_point(|&c| c <= u);
        i.min(self.light_cdf.len() - 1)
    }
}

impl<R: Real> Distributed<R> {
    /// The frame of the camera at shutter fraction `tau`.
    pub fn camera_at(&self, world: &World<R>, tau: R) -> CameraFrame<R> {
        let Some(m) = &self.camera_motion else {
            return CameraFrame {
                origin: R::V3::zero(),
                camera: world.camera,
                unit_right: self.unit_right,
                unit_up: self.unit_up,
                look_distance: self.look_distance,
            };
        };
        let origin = m.delta_position * tau;
        let look = m.look_at + m.delta_look_at * tau;
        let fwd = look - origin;
        let look_distance = fwd.length();
        let f = fwd * (R::ONE / look_distance);
        let r = f.cross(m.up).normalize();
        let u = r.cross(f);
        let fov = m.fov_y + m.delta_fov_y * tau.to_f64();
        let (s, c) = crate::sampling::sin_cos_turns(fov / 720.0);
        let t = R::from_f64(s / c);
        CameraFrame {
            origin,
            camera: crate::world::Camera {
                forward: f,
                right: r * (t * m.aspect),
                up: u * t,
                ..world.camera
            },
            unit_right: r,
            unit_up: u,
            look_distance,
        }
    }
}

pub(crate) fn sub64(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// What `World::build` needs to decide and fill [`Distributed`].
pub(crate) struct Timing {
    pub open: f64,
    pub close: f64,
}

impl Timing {
    pub fn of(desc: &SceneDesc, frame: u32) -> Self {
        let (open, close) = desc.camera.shutter();
        Timing {
            open: frame as f64 + open,
            close: frame as f64 + close,
        }
    }
}

/// Camera motion over the shutter, if the pose changes.
pub(crate) fn camera_motion<R: Real>(
    desc: &SceneDesc,
    a: &CameraPose,
    b: &CameraPose,
    aspect: f64,
) -> Option<CameraMotion<R>> {
    if a == b {
        return None;
    }
    let o = a.position.0;
    Some(CameraMotion {
        delta_position: R::V3::from_array(sub64(b.position.0, o)),
        look_at: R::V3::from_array(sub64(a.look_at.0, o)),
        delta_look_at: R::V3::from_array(sub64(b.look_at.0, a.look_at.0)),
        fov_y: a.fov_y.0,
        delta_fov_y: b.fov_y.0 - a.fov_y.0,
        up: R::V3::from_array(desc.camera.up.0).normalize(),
        aspect: R::from_f64(aspect),
    })
}

/// Lights in file order, camera-relative.
pub(crate) fn lights<R: Real>(desc: &SceneDesc, origin: &[f64; 3]) -> Vec<Light<R>> {
    let rel = |p: [f64; 3]| R::V3::from_array(sub64(p, *origin));
    let mut first = 0;
    desc.lights
        .iter()
        .map(|l| {
            let geom = match l.shape {
                LightShape::Point => LightGeom::Point(rel(l.position.0)),
                LightShape::Quad {
                    corner,
                    edge_u,
                    edge_v,
                } => LightGeom::Quad {
                    corner: rel(corner.0),
                    edge_u: R::V3::from_array(edge_u.0),
                    edge_v: R::V3::from_array(edge_v.0),
                },
                LightShape::Sphere { center, radius } => LightGeom::Sphere {
                    center: rel(center.0),
                    radius: R::from_f64(radius),
                },
            };
            let light = Light {
                geom,
                diffuse: R::V3::from_array(l.diffuse.0),
                specular: R::V3::from_array(l.specular.0),
                samples: l.samples,
                first_sample: first,
            };
            first += l.samples;
            light
        })
        .collect()
}

/// The box of a sphere swept from `c` by `delta`, widened by rounding.
pub(crate) fn swept_box<R: Real>(lo: [f64; 3], hi: [f64; 3], delta: [f64; 3]) -> (R::V3, R::V3) {
    let mut a = [0.0; 3];
    let mut b = [0.0; 3];
    for k in 0..3 {
        let (l, h) = (lo[k].min(lo[k] + delta[k]), hi[k].max(hi[k] + delta[k]));
        let pad = (l.abs().max(h.abs())) * 1e-6 + 1e-12;
        a[k] = l - pad;
        b[k] = h + pad;
    }
    (R::V3::from_array(a), R::V3::from_array(b))
}
