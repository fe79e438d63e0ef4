//! Render-ready scene state for one precision and one frame.
//!
//! Built from a [`SceneDesc`] in `f64` and only then rounded to the render
//! precision, *relative to the camera*: every position is stored as an
//! offset from the camera. Points near the camera, where precision matters
//! most, then have small coordinates, so a 1e-4 sphere placed 1e5 from the
//! world origin is still resolved in `f32`.
//!
//! Here the types and the build; `triangles.rs` places mesh objects into
//! a world's triangles; `query.rs` answers rays (nearest hit, occlusion,
//! surface), through the tree that `accel.rs` builds when the scene has
//! one. The world sits above `accel` and `bvh`: it owns the tree and the
//! primitives, and neither of them knows the `World`.

mod instances;
mod query;
mod triangles;

use crate::bsdf::Bsdf;
use crate::bvh::Bvh;
use crate::distributed::{self, Distributed, Lens, MovingMesh, MovingSphere, PathScene, Timing};
use crate::geometry::{Plane, PlanePack, Sphere, SpherePack};
use crate::math::{Ray, Real, Vector3};
use crate::scene::{FILE_MATERIALS, Integrator, ObjectDesc, RenderSettings, SceneDesc, Vec3};
use crate::triangle::{Triangle, TriangleShading, gather, gather_all};
use triangles::TriangleSet;
pub use triangles::VertexAttrs;

pub use instances::{Affine3, Instance, InstancedMesh, Instances};
pub use query::PlacedTriangle;

pub use crate::light::PointLight;
pub use crate::material::Material;
use crate::material::{NO_PBR, Pbr};

/// Pinhole camera at the (camera-relative) origin.
#[derive(Clone, Copy, Debug)]
pub struct Camera<R: Real> {
    pub forward: R::V3,
    /// right * tan(fov_y/2) * aspect
    pub right: R::V3,
    /// up * tan(fov_y/2)
    pub up: R::V3,
    pub inv_width: R,
    pub inv_height: R,
}

impl<R: Real> Camera<R> {
    /// The ray through raster point (sx, sy): direction
    /// normalize(f + (2 sx/W - 1) t (W/H) r + (1 - 2 sy/H) t u).
    #[inline(always)]
    pub fn ray(&self, sx: R, sy: R) -> Ray<R> {
        let a = R::TWO * sx * self.inv_width - R::ONE;
        let b = R::ONE - R::TWO * sy * self.inv_height;
        let d = self.forward + self.right * a + self.up * b;
        Ray::new(R::V3::zero(), d.normalize())
    }
}

/// Which optional stages a scene can reach, so the renderers skip the rest.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Features {
    pub reflection: bool,
    pub refraction: bool,
}

impl Features {
    /// Notes what a material in use can reach.
    pub fn note<R: Real>(&mut self, m: &Material<R>, max_depth: u32) {
        // Depth 0 reaches no secondary ray at all.
        self.reflection |= m.reflectivity > R::ZERO && max_depth > 0;
        self.refraction |= m.transparency > R::ZERO && max_depth > 0;
    }

    /// Notes what a file material's textures may make it reach at some hit
    /// beyond its factors (`Pbr::whitted` per hit): a metallic-roughness
    /// texture may lower the roughness of a metal to a mirror, and a
    /// texture, vertex colours or a lower metallic may make a BLEND or
    /// transmissive surface see-through. The GPU compiles out what no
    /// material can reach (`HAS_REFLECTION`, `HAS_REFRACTION`).
    pub fn note_pbr(&mut self, p: &crate::material::Pbr, max_depth: u32) {
        let deep = max_depth > 0;
        self.reflection |= deep && p.metallic > 0.0 && p.metallic_roughness_texture.is_some();
        let alpha_varies =
            p.base_color_texture.is_some() || p.vertex_colors || p.alpha_texture.is_some();
        self.refraction |= deep
            && ((p.alpha_mode == crate::material::AlphaMode::Blend && alpha_varies)
                || (p.transmission > 0.0 && p.metallic_roughness_texture.is_some()));
    }
}

#[derive(Clone, Debug)]
pub struct World<R: Real> {
    pub spheres: Vec<Sphere<R>>,
    /// The same spheres four to a pack, for the intersection loops.
    pub sphere_packs: Vec<SpherePack<R>>,
    pub planes: Vec<Plane<R>>,
    /// The same planes four to a pack, for the intersection loops.
    pub plane_packs: Vec<PlanePack<R>>,
    /// Mesh triangles' vertex positions (shared by the triangles that
    /// meet there) ...
    pub(crate) positions: Vec<R::V3>,
    /// ... each triangle's corners in them (and in `vertex_normals`) ...
    pub(crate) corners: Vec<[u32; 3]>,
    /// ... and the triangles gathered (what traversal touches), except in
    /// a big world (at least [`GIVE_UP_TRIANGLES_FROM`] `f32` triangles
    /// and no spheres or instances), whose tree reads them from their
    /// corners at each test: read them by [`World::triangle`] ...
    unpacked_triangles: Vec<Triangle<R>>,
    /// Their unit geometric normals, where the world keeps its triangles
    /// in the array (below [`GIVE_UP_TRIANGLES_FROM`]; else empty and
    /// computed at each hit): [`World::triangle_normal`] ...
    unit_normals: Vec<R::V3>,
    /// ... and, at the same index, what shading needs ...
    pub triangle_shading: Vec<TriangleShading>,
    /// Unit vertex normals at the positions' indices, or none
    /// ([`crate::triangle::VertexNormals`]).
    pub vertex_normals: Vec<R::V3>,
    /// Bounding volume hierarchy over spheres and triangles, when the scene
    /// has meshes or many spheres (see `accel.rs`); planes stay outside it.
    /// Its leaf order is the triangles': change it through
    /// [`World::set_accel`], which reorders them with it.
    pub accel: Option<Bvh>,
    /// Meshes placed many times, stored once (the tree's `PrimId::INSTANCE`s).
    pub instances: Instances<R>,
    /// Mesh triangles dropped at build because they have no area.
    pub degenerate_triangles: usize,
    pub materials: Vec<Material<R>>,
    /// The path integrator's BSDF of each material (`[bsdf.NAME]`, else
    /// mapped from the Blinn-Phong material: `Bsdf::from_material`).
    pub bsdfs: Vec<Bsdf<R>>,
    /// Textures and glTF parameters of model files' materials
    /// (`Material::pbr` indexes this) ...
    pub pbr: Vec<std::sync::Arc<crate::material::Pbr>>,
    /// ... and the texture coordinates and colours of their triangles.
    pub attrs: VertexAttrs,
    pub lights: Vec<PointLight<R>>,
    pub ambient: R::V3,
    pub background: R::V3,
    pub camera: Camera<R>,
    pub settings: RenderSettings,
    pub features: Features,
    /// World-space position of the camera, which is this world's origin.
    pub camera_position: [f64; 3],
    /// Distributed ray tracing (area lights, cones, lens, motion), only
    /// for scenes that use it: they render through its own path.
    pub dist: Option<Box<Distributed<R>>>,
}

fn v<R: Real>(a: &Vec3) -> R::V3 {
    R::V3::from_array(a.0)
}

fn rel<R: Real>(p: &Vec3, origin: &[f64; 3]) -> R::V3 {
    R::V3::from_array([p.0[0] - origin[0], p.0[1] - origin[1], p.0[2] - origin[2]])
}

/// What a built frame holds, for reports (`tessera render --json`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct WorldStats {
    pub spheres: usize,
    pub planes: usize,
    /// Triangles stored: the top level's plus each instanced mesh's once ...
    pub triangles: usize,
    /// ... and as the camera sees them: each instanced mesh once per placement.
    pub placed_triangles: u64,
    pub instances: usize,
    /// Distinct texture images, and their texels' bytes (8-bit RGBA).
    pub textures: usize,
    pub texture_bytes: u64,
    /// The path integrator's environment image, where it has one: its
    /// name, width, height and bytes held (texels and sampling tables).
    pub environment: Option<(String, u32, u32, u64)>,
    /// What the trees took to build: the world's and each instanced
    /// mesh's (binned SAH, the 4-wide collapse and flattening).
    pub tree_build_time: std::time::Duration,
}

/// `f32` worlds of at least this many triangles (and no spheres or
/// instances) hold them as corners into shared vertices alone, their
/// tree built over those (`Bvh::build_indexed`) and tested without
/// packets, and compute a hit's geometric normal: 104 bytes a triangle
/// less (gathered triangle 48, packet 40, unit normal 16). Smaller ones
/// keep the gathered triangles, their packets and unit normals, for
/// speed: with the latter two, the Cornell box took 3.7% less time
/// path-traced and 2.7% less Whitted, DamagedHelmet path-traced 1.5%
/// (2-core VM, medians of 8-12 interleaved runs).
pub const GIVE_UP_TRIANGLES_FROM: usize = 1 << 18;

impl<R: Real> World<R> {
    /// Every image its model materials read, once (a texture shared by
    /// materials is one `Arc`), in first-use order: what the GPU's texel
    /// pack uploads and what [`World::stats`] counts.
    pub fn texture_images(&self) -> Vec<&std::sync::Arc<crate::texture::Image>> {
        let mut images: Vec<&std::sync::Arc<crate::texture::Image>> = Vec::new();
        for t in self.pbr.iter().flat_map(|p| p.textures()) {
            if !images.iter().any(|i| std::sync::Arc::ptr_eq(i, &t.image)) {
                images.push(&t.image);
            }
        }
        images
    }

    /// Makes the mip levels of every texture its model materials read
    /// (`Image::levels`, made once an image and decoding), the images in
    /// parallel: a renderer calls it before tracing, in its own threads,
    /// so that no thread waits while another makes them at its first hit.
    pub fn make_texture_levels(&self) {
        use rayon::prelude::*;
        // Each image and decoding once: two tasks on one chain would both
        // make it.
        self.texture_decodings()
            .par_iter()
            .for_each(|(image, srgb)| {
                image.levels(*srgb);
            });
    }

    /// Every image its model materials read with each decoding it is read
    /// with (sRGB colour or data), once, in first-use order: one mip chain
    /// each, and what the GPU's texel pack holds.
    pub fn texture_decodings(&self) -> Vec<(&std::sync::Arc<crate::texture::Image>, bool)> {
        let mut out: Vec<(&std::sync::Arc<crate::texture::Image>, bool)> = Vec::new();
        for t in self.pbr.iter().flat_map(|p| p.textures()) {
            if !out
                .iter()
                .any(|(i, srgb)| std::sync::Arc::ptr_eq(i, &t.image) && *srgb == t.srgb)
            {
                out.push((&t.image, t.srgb));
            }
        }
        out
    }

    pub fn stats(&self) -> WorldStats {
        let mesh_triangles: usize = self
            .instances
            .meshes
            .iter()
            .map(|m| m.triangles.len())
            .sum();
        let placed: u64 = self
            .instances
            .list
            .iter()
            .map(|i| self.instances.meshes[i.mesh as usize].triangles.len() as u64)
            .sum();
        let images = self.texture_images();
        WorldStats {
            spheres: self.spheres.len(),
            planes: self.planes.len(),
            triangles: self.triangle_count() + mesh_triangles,
            placed_triangles: self.triangle_count() as u64 + placed,
            instances: self.instances.list.len(),
            textures: images.len(),
            texture_bytes: images.iter().map(|i| 4 * i.texels.len() as u64).sum(),
            environment: self
                .dist
                .as_ref()
                .and_then(|d| d.path.as_ref())
                .and_then(|p| p.environment_map.as_ref())
                .map(|e| (e.name.clone(), e.width, e.height, e.bytes() as u64)),
            tree_build_time: self
                .accel
                .iter()
                .chain(self.instances.meshes.iter().map(|m| &m.tree))
                .map(|t| t.stats.build_time)
                .sum(),
        }
    }

    /// Builds the render-ready state of `desc` for `settings` (validated by
    /// the caller) and `frame`.
    pub fn build(desc: &SceneDesc, settings: &RenderSettings, frame: u32) -> Self {
        Self::build_from(desc, desc.models(), settings, frame)
    }

    /// As [`World::build`], with the objects' loaded models given apart
    /// (`models[i]`: object i's; `desc`'s own are not read). They are
    /// dropped once their triangles are placed, before the tree is built:
    /// given the only references (`SceneDesc::take_models`), a big model's
    /// memory is free again for the build, the peak of a big mesh's render.
    pub fn build_from(
        desc: &SceneDesc,
        models: Vec<Option<std::sync::Arc<crate::mesh::Mesh>>>,
        settings: &RenderSettings,
        frame: u32,
    ) -> Self {
        assert_eq!(models.len(), desc.objects.len(), "a model per object");
        // The shutter's opening; [0, 0] (the default) is the frame itself.
        let time = Timing::of(desc, frame);
        let cam = desc.camera.at_time(time.open);
        let origin = cam.position.0;
        // Camera basis in f64, then rounded.
        let f = normalize64(sub64(cam.look_at.0, origin));
        let r = normalize64(cross64(f, desc.camera.up.0));
        let u = cross64(r, f);
        let t = (cam.fov_y.0.to_radians() * 0.5).tan();
        let aspect = settings.width as f64 / settings.height as f64;
        let camera = Camera {
            forward: R::V3::from_array(f),
            right: R::V3::from_array(r.map(|x| x * t * aspect)),
            up: R::V3::from_array(u.map(|x| x * t)),
            inv_width: R::from_f64(1.0 / settings.width as f64),
            inv_height: R::from_f64(1.0 / settings.height as f64),
        };

        let mut materials: Vec<Material<R>> = desc
            .materials
            .iter()
            .map(|(_, m)| Material::from_desc(m))
            .collect();

        let mut spheres = Vec::new();
        let mut moving_spheres = Vec::new();
        let mut moving_meshes = Vec::new();
        let mut planes = Vec::new();
        let mut tris = TriangleSet {
            instancing: true,
            ..Default::default()
        };
        let mut features = Features::default();
        for ((o, &mat), model) in desc.objects.iter().zip(&desc.object_materials).zip(&models) {
            let model = model.as_deref();
            if mat != FILE_MATERIALS {
                features.note(&materials[mat as usize], settings.max_depth);
            }
            match o {
                ObjectDesc::Sphere {
                    center,
                    radius,
                    keyframes,
                    ..
                } => {
                    let c = ObjectDesc::sphere_center_at(center, keyframes, time.open);
                    let sphere = Sphere {
                        center: rel::<R>(&c, &origin),
                        radius: R::from_f64(radius.0),
                        material: mat,
                    };
                    let c1 = ObjectDesc::sphere_center_at(center, keyframes, time.close);
                    if c1 == c {
                        spheres.push(sphere);
                    } else {
                        let delta = distributed::sub64(c1.0, c.0);
                        let lo = distributed::sub64(c.0, origin).map(|x| x - radius.0);
                        let hi = distributed::sub64(c.0, origin).map(|x| x + radius.0);
                        let (lo, hi) = distributed::swept_box::<R>(lo, hi, delta);
                        moving_spheres.push(MovingSphere {
                            sphere,
                            delta: R::V3::from_array(delta),
                            lo,
                            hi,
                        });
                    }
                }
                ObjectDesc::Plane {
                    normal, distance, ..
                } => {
                    let n = normal.0;
                    let d = distance.0 - (n[0] * origin[0] + n[1] * origin[1] + n[2] * origin[2]);
                    planes.push(Plane {
                        normal: R::V3::from_array(n),
                        distance: R::from_f64(d),
                        material: mat,
                    })
                }
                ObjectDesc::Mesh(m) if m.keyframes.is_empty() => tris.add_mesh(
                    m,
                    model,
                    mat,
                    &mut materials,
                    &mut features,
                    settings.max_depth,
                    origin,
                ),
                ObjectDesc::Mesh(m) => {
                    let mut placed = m.clone();
                    placed.translate = m.translate_at(time.open);
                    let t1 = m.translate_at(time.close);
                    if t1 == placed.translate {
                        tris.add_mesh(
                            &placed,
                            model,
                            mat,
                            &mut materials,
                            &mut features,
                            settings.max_depth,
                            origin,
                        );
                    } else {
                        // Its own world (materials as the main one's so
                        // far, the file's appended): a tree of its own.
                        let mut own = TriangleSet::default();
                        let mut own_materials = materials.clone();
                        own.add_mesh(
                            &placed,
                            model,
                            mat,
                            &mut own_materials,
                            &mut features,
                            settings.max_depth,
                            origin,
                        );
                        let delta = distributed::sub64(t1.0, placed.translate.0);
                        moving_meshes.push((own, own_materials, delta));
                    }
                }
            }
        }

        drop(models);

        // Total internal reflection sends transparency into a reflected ray.
        if features.refraction {
            features.reflection = true;
        }

        let lights = desc
            .lights
            .iter()
            .filter(|l| !l.shape.is_area())
            .map(|l| PointLight {
                position: rel::<R>(&l.position, &origin),
                diffuse: v::<R>(&l.diffuse),
                specular: v::<R>(&l.specular),
            })
            .collect();

        let mut world = World {
            sphere_packs: SpherePack::pack(&spheres),
            spheres,
            plane_packs: PlanePack::pack(&planes),
            planes,
            positions: tris.positions,
            corners: tris.corners,
            unpacked_triangles: Vec::new(),
            unit_normals: Vec::new(),
            triangle_shading: tris.shading,
            vertex_normals: tris.vertex_normals,
            accel: None,
            degenerate_triangles: tris.degenerate + tris.instances.dropped,
            instances: tris.instances,
            bsdfs: bsdfs_of(desc, &materials, &tris.pbr),
            materials,
            pbr: tris.pbr,
            attrs: tris.attrs,
            lights,
            ambient: v::<R>(&desc.world.ambient),
            background: v::<R>(&desc.world.background),
            camera,
            settings: *settings,
            features,
            camera_position: origin,
            dist: None,
        };
        world.set_accel(None);

        // Distributed ray tracing, only where the scene asks for it.
        let area_lights = desc.lights.iter().any(|l| l.shape.is_area());
        let cones = world
            .materials
            .iter()
            .chain(moving_meshes.iter().flat_map(|(_, m, _)| m.iter()))
            .any(|m| m.gloss_cos < R::ONE || m.translucency_cos < R::ONE);
        let lens = (desc.camera.aperture.0 > 0.0).then(|| Lens {
            aperture: R::from_f64(desc.camera.aperture.0),
            focus_distance: desc.camera.focus_distance.map(|f| R::from_f64(f.0)),
        });
        let camera_motion =
            distributed::camera_motion::<R>(desc, &cam, &desc.camera.at_time(time.close), aspect);
        let path = settings.integrator == Integrator::Path;
        if path
            || area_lights
            || cones
            || lens.is_some()
            || camera_motion.is_some()
            || !moving_spheres.is_empty()
            || !moving_meshes.is_empty()
        {
            let blur =
                camera_motion.is_some() || !moving_spheres.is_empty() || !moving_meshes.is_empty();
            let moving_meshes = moving_meshes
                .into_iter()
                .map(|(set, mats, delta)| {
                    let mut own = World {
                        sphere_packs: Vec::new(),
                        spheres: Vec::new(),
                        planes: Vec::new(),
                        plane_packs: Vec::new(),
                        positions: set.positions,
                        corners: set.corners,
                        unpacked_triangles: Vec::new(),
                        unit_normals: Vec::new(),
                        triangle_shading: set.shading,
                        vertex_normals: set.vertex_normals,
                        accel: None,
                        instances: set.instances,
                        degenerate_triangles: set.degenerate,
                        bsdfs: bsdfs_of(desc, &mats, &set.pbr),
                        materials: mats,
                        pbr: set.pbr,
                        attrs: set.attrs,
                        lights: Vec::new(),
                        dist: None,
                        ..world.clone_settings()
                    };
                    own.set_accel(None);
                    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
                    for t in own.triangles() {
                        for v in t.vertices() {
                            let v = v.to_array();
                            for k in 0..3 {
                                lo[k] = lo[k].min(v[k]);
                                hi[k] = hi[k].max(v[k]);
                            }
                        }
                    }
                    let (lo, hi) = distributed::swept_box::<R>(lo, hi, delta);
                    MovingMesh {
                        world: own,
                        delta: R::V3::from_array(delta),
                        lo,
                        hi,
                    }
                })
                .collect();
            let mut lights = distributed::lights::<R>(desc, &origin);
            if path {
                // A model file's lights in physical units (1/d² falloff).
                for (l, d) in lights.iter_mut().zip(&desc.lights) {
                    if let Some(c) = d.path_radiance {
                        l.diffuse = R::V3::from_array(c.0);
                        l.specular = l.diffuse;
                    }
                    // Spot cones and directional lights: their own kinds.
                    match d.path_kind {
                        Some(crate::scene::PathLightKind::Spot {
                            direction,
                            cos_inner,
                            cos_outer,
                        }) => {
                            let scale = 1.0 / (cos_inner - cos_outer).max(0.001);
                            l.geom = crate::light::LightGeom::Spot {
                                position: rel::<R>(&d.position, &origin),
                                direction: v::<R>(&direction),
                                scale: R::from_f64(scale),
                                offset: R::from_f64(-cos_outer * scale),
                            };
                        }
                        Some(crate::scene::PathLightKind::Directional {
                            direction,
                            irradiance,
                            radius,
                        }) => {
                            // Its power covers the whole scene, not only
                            // its model (which may be a lamp alone).
                            let radius = radius.max(scene_radius(&world));
                            // A world of planes alone: the unit sphere.
                            let radius = if radius > 0.0 { radius } else { 1.0 };
                            l.geom = crate::light::LightGeom::Directional {
                                direction: v::<R>(&direction),
                                radius: R::from_f64(radius),
                            };
                            l.diffuse = v::<R>(&irradiance);
                            l.specular = l.diffuse;
                        }
                        None => {}
                    }
                }
            }
            let mut environment = v::<R>(&desc.world.environment.colour());
            let map = desc.world.environment_map.clone();
            if path && desc.world.default_lighting {
                // A model file's default lighting: the sky (or the image
                // given), not the headlight (the last light, the only one).
                lights.clear();
                if map.is_none() {
                    environment = R::V3::splat(R::from_f64(crate::scene::DEFAULT_SKY));
                }
            }
            let path = path.then(|| {
                // Emissive triangles are lights too (`crate::emitters`).
                let power = crate::emitters::material_power(&world);
                let emitters = crate::emitters::collect(&world, &power);
                // A world of planes alone has no size: the unit sphere
                // then stands for it (the image is still light-sampled).
                let map = map.map(|m| (m, scene_radius(&world).max(1.0)));
                PathScene::new(&lights, environment, map, emitters, &power)
            });
            world.dist = Some(Box::new(Distributed {
                path,
                lights,
                area_lights,
                cones,
                lens,
                camera_motion,
                moving_spheres,
                moving_meshes,
                blur,
                unit_right: R::V3::from_array(r),
                unit_up: R::V3::from_array(u),
                look_distance: R::from_f64(
                    sub64(cam.look_at.0, origin)
                        .iter()
                        .map(|x| x * x)
                        .sum::<f64>()
                        .sqrt(),
                ),
            }));
        }
        world
    }

    /// Rebuilds (`Some(true)`), drops (`Some(false)`) or re-decides (`None`)
    /// the acceleration structure. Without one, every query tests every
    /// primitive: the brute-force reference the tree is checked against.
    pub fn set_accel(&mut self, force: Option<bool>) {
        let n = self.corners.len();
        // A big mesh is held as corners into shared vertices alone
        // (memory); a small one's triangles are gathered once, for the
        // packets' 4-wide test and for hits that read them directly.
        let big = std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>()
            && n >= GIVE_UP_TRIANGLES_FROM
            && self.spheres.is_empty()
            && self.instances.list.is_empty()
            && force != Some(false);
        if big {
            self.unpacked_triangles = Vec::new();
        } else if self.unpacked_triangles.len() != n {
            self.unpacked_triangles = gather_all(&self.positions, &self.corners);
        }
        self.accel = crate::accel::build(
            &self.spheres,
            &self.instances.boxes(),
            crate::accel::TriangleArrays {
                positions: &self.positions,
                corners: &mut self.corners,
                shading: &mut self.triangle_shading,
                triangles: &mut self.unpacked_triangles,
            },
            force,
        );
        // The same f32 (or f64) operations a hit would do, once.
        self.unit_normals = self.unpacked_triangles.iter().map(|t| t.normal()).collect();
    }

    /// How many triangles the world holds itself (instanced meshes' apart).
    #[inline]
    pub fn triangle_count(&self) -> usize {
        self.corners.len()
    }

    /// Triangle `index` of the world's own (by value: a big world's is
    /// gathered from its corners).
    #[inline]
    pub fn triangle(&self, index: usize) -> Triangle<R> {
        match self.unpacked_triangles.get(index) {
            Some(t) => *t,
            None => gather(&self.positions, self.corners[index]),
        }
    }

    /// Triangle `index`'s unit geometric normal (`Triangle::normal`):
    /// kept for a small world, computed for a big one.
    #[inline]
    pub fn triangle_normal(&self, index: usize) -> R::V3 {
        self.kept_normal(index)
            .unwrap_or_else(|| self.triangle(index).normal())
    }

    /// Triangle `index`'s unit normal where the world keeps it (for a
    /// caller that holds the triangle already and computes it otherwise).
    #[inline]
    pub(crate) fn kept_normal(&self, index: usize) -> Option<R::V3> {
        self.unit_normals.get(index).copied()
    }

    /// Every triangle of the world's own, in id order.
    pub fn triangles(&self) -> impl ExactSizeIterator<Item = Triangle<R>> + '_ {
        (0..self.triangle_count()).map(|i| self.triangle(i))
    }

    /// The triangles as one array, where the world keeps them gathered
    /// (`None` for a big world, which keeps only their corners).
    pub fn gathered_triangles(&self) -> Option<&[Triangle<R>]> {
        (self.unpacked_triangles.len() == self.triangle_count())
            .then_some(self.unpacked_triangles.as_slice())
    }

    /// Bytes of the triangle data (vertices, corners, the gathered
    /// triangles and their normals where kept, shading and the vertex
    /// normals; the tree's packets are the tree's bytes).
    pub fn triangle_bytes(&self) -> usize {
        std::mem::size_of_val(self.positions.as_slice())
            + std::mem::size_of_val(self.corners.as_slice())
            + std::mem::size_of_val(self.unpacked_triangles.as_slice())
            + std::mem::size_of_val(self.unit_normals.as_slice())
            + std::mem::size_of_val(self.triangle_shading.as_slice())
            + std::mem::size_of_val(self.vertex_normals.as_slice())
    }

    /// A world with this one's settings, camera and colours and nothing in it.
    fn clone_settings(&self) -> Self {
        World {
            spheres: Vec::new(),
            sphere_packs: Vec::new(),
            planes: Vec::new(),
            plane_packs: Vec::new(),
            positions: Vec::new(),
            corners: Vec::new(),
            unpacked_triangles: Vec::new(),
            unit_normals: Vec::new(),
            triangle_shading: Vec::new(),
            vertex_normals: Vec::new(),
            accel: None,
            instances: Instances::default(),
            degenerate_triangles: 0,
            materials: Vec::new(),
            bsdfs: Vec::new(),
            pbr: Vec::new(),
            attrs: VertexAttrs::default(),
            lights: Vec::new(),
            ambient: self.ambient,
            background: self.background,
            camera: self.camera,
            settings: self.settings,
            features: self.features,
            camera_position: self.camera_position,
            dist: None,
        }
    }
}

/// Half the diagonal of the box around the world's bounded primitives
/// (spheres, triangles, instances; planes are unbounded): 0 for none.
fn scene_radius<R: Real>(world: &World<R>) -> f64 {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    let mut add = |p: [f64; 3], r: f64| {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k] - r);
            hi[k] = hi[k].max(p[k] + r);
        }
    };
    for s in &world.spheres {
        add(s.center.to_array(), s.radius.to_f64());
    }
    for t in world.triangles() {
        for v in t.vertices() {
            add(v.to_array(), 0.0);
        }
    }
    for b in world.instances.boxes() {
        add(b.min.to_array().map(f64::from), 0.0);
        add(b.max.to_array().map(f64::from), 0.0);
    }
    if !(lo[0] <= hi[0]) {
        return 0.0;
    }
    0.5 * (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt()
}

/// Each material's BSDF: the file's materials come first (in
/// `desc.materials`' order, with their `[bsdf.NAME]`), model files' after
/// (glTF's parameters: `Pbr::bsdf_of`).
fn bsdfs_of<R: Real>(
    desc: &SceneDesc,
    materials: &[Material<R>],
    pbr: &[std::sync::Arc<Pbr>],
) -> Vec<Bsdf<R>> {
    materials
        .iter()
        .enumerate()
        .map(|(i, m)| match desc.bsdfs.get(i) {
            Some(Some(b)) => Bsdf::from_desc(b),
            _ if m.pbr != NO_PBR => pbr[m.pbr as usize].bsdf_of(m),
            _ => Bsdf::from_material(m),
        })
        .collect()
}

fn sub64(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross64(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn normalize64(a: [f64; 3]) -> [f64; 3] {
    let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    a.map(|x| x / l)
}
