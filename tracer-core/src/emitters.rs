//! Emissive triangles as lights of the path integrator (docs/path-tracing.md):
//! every triangle of the static world (instances included) whose material
//! emits joins the power-proportional light selection, with power
//! pi x area x the luminance of the material's mean emission (the factor
//! times the emissive texture's mean texel), and is sampled uniformly by
//! area, its radiance the texel at the sampled point. Triangles emit from
//! the side their outward normal faces, as a hit's emission does.
//!
//! The probability of choosing a triangle is its area times its material's
//! [`PathScene::emit_density`](crate::distributed::PathScene), so the
//! solid-angle density of a point on it seen from distance d at cosine
//! cos is `density x d² / cos`: what a BSDF-sampled hit needs for its MIS
//! weight, from the hit alone, without a table indexed by triangle.

use crate::geometry::PrimId;
use crate::light::LightSample;
use crate::material::NO_PBR;
use crate::math::{Real, Vector3};
use crate::world::World;

/// One emissive triangle: vertex `a` and the edges from it.
#[derive(Clone, Copy, Debug)]
pub struct TriEmitter<R: Real> {
    pub a: R::V3,
    pub e1: R::V3,
    pub e2: R::V3,
    /// Unit outward normal: the side that emits.
    pub n: R::V3,
    pub material: u32,
    /// Its id in the static world (where its emission texture is read).
    pub id: PrimId,
    /// pi x area x mean emitted luminance.
    pub power: f64,
}

/// pi x the luminance (the channels' mean) of each material's mean
/// emission over its surface: 0 for materials that do not emit.
pub fn material_power<R: Real>(world: &World<R>) -> Vec<f64> {
    world
        .bsdfs
        .iter()
        .zip(&world.materials)
        .map(|(b, m)| {
            let mut e = b.emission.to_array();
            if m.pbr != NO_PBR
                && let Some(t) = &world.pbr[m.pbr as usize].emissive_texture
            {
                let mean = t.mean();
                e = std::array::from_fn(|i| e[i] * mean[i]);
            }
            let lum = (e[0] + e[1] + e[2]) / 3.0;
            if lum > 0.0 {
                std::f64::consts::PI * lum
            } else {
                0.0
            }
        })
        .collect()
}

/// The emissive triangles of `world` (its own, then its instances'),
/// given each material's [`material_power`].
pub fn collect<R: Real>(world: &World<R>, power: &[f64]) -> Vec<TriEmitter<R>> {
    let mut out = Vec::new();
    if !power.iter().any(|&p| p > 0.0) {
        return out;
    }
    let mut push = |v: [R::V3; 3], n: R::V3, material: u32, id: PrimId| {
        let (e1, e2) = (v[1] - v[0], v[2] - v[0]);
        let c = (e1.to_array(), e2.to_array());
        let x = [
            c.0[1] * c.1[2] - c.0[2] * c.1[1],
            c.0[2] * c.1[0] - c.0[0] * c.1[2],
            c.0[0] * c.1[1] - c.0[1] * c.1[0],
        ];
        let area = 0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
        if area > 0.0 {
            out.push(TriEmitter {
                a: v[0],
                e1,
                e2,
                n,
                material,
                id,
                power: area * power[material as usize],
            });
        }
    };
    for (i, (t, s)) in world.triangles().zip(&world.triangle_shading).enumerate() {
        if power[s.material as usize] > 0.0 {
            push(
                t.vertices(),
                t.normal(),
                s.material,
                PrimId::new(PrimId::TRIANGLE, i as u32),
            );
        }
    }
    let inst = &world.instances;
    for placed in &inst.list {
        let m = &inst.meshes[placed.mesh as usize];
        for (k, (t, s)) in m.triangles.iter().zip(&m.shading).enumerate() {
            if power[s.material as usize] > 0.0 {
                push(
                    t.vertices().map(|v| placed.to_world.point(v)),
                    placed.to_object.transposed(t.normal()).normalize(),
                    s.material,
                    PrimId::new(PrimId::INSTANCE_TRIANGLE, placed.first + k as u32),
                );
            }
        }
    }
    out
}

impl<R: Real> TriEmitter<R> {
    /// A point uniform by area for uniform numbers (u, v), seen from `p`;
    /// `density` is its material's selection probability per unit area.
    /// `None` where `p` is behind it (it emits nothing that way).
    pub fn sample_li(
        &self,
        world: &World<R>,
        p: R::V3,
        u: f32,
        v: f32,
        density: R,
    ) -> Option<LightSample<R>> {
        let su = R::from_f64(u as f64).sqrt();
        let b2 = R::from_f64(v as f64) * su;
        let x = self.a + self.e1 * (su - b2) + self.e2 * b2;
        let d = x - p;
        let dist = d.length();
        if !(dist > R::ZERO) {
            return None;
        }
        let wi = d * (R::ONE / dist);
        let cos_l = -self.n.dot(wi);
        if !(cos_l > R::ZERO) {
            return None;
        }
        Some(LightSample {
            wi,
            dist,
            li: crate::render::step::emission_at(world, self.id, x, self.material),
            pdf: density * dist * dist / cos_l,
        })
    }
}
