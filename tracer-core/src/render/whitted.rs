//! The thesis's Whitted model, exactly as the scene-format contract states it:
//!
//! colour = ambient * m.ambient
//!        + sum over unblocked lights (max(N.L,0) l.diffuse m.diffuse + max(N.H,0)^shininess l.specular m.specular)
//!        + reflectivity * reflected + transparency * refracted
//!
//! with total internal reflection sending the transparency weight to the
//! reflected ray, and `max_depth` bounding the generations of secondary rays.
//! Generic over precision: `f32` is the fast path, `f64` the reference.

use crate::film::RayCounts;
use crate::geometry::PrimId;
use crate::math::{offset_origin, Ray, Real, Vector3};
use crate::world::World;

/// Colour seen along `ray`, which starts on primitive `skip` (or none) and
/// is of generation `depth` (primary rays are 0).
pub fn trace<R: Real>(world: &World<R>, ray: &Ray<R>, depth: u32, skip: PrimId, rays: &mut RayCounts) -> R::V3 {
    let Some((t, id)) = world.closest_hit(ray, skip) else {
        return world.background;
    };
    let (p, n_out, mat) = world.surface(id, ray.at(t));
    let m = &world.materials[mat as usize];
    let v = -ray.dir;
    let cos_out = n_out.dot(v);
    // Entering: arriving against the outward normal.
    let entering = cos_out >= R::ZERO;
    let n = if entering { n_out } else { -n_out };
    // Shading normal: differs from n only on smoothly shaded triangles.
    let ns = world.shading_normal(id, p, n, v);
    let cos_i = ns.dot(v);

    let mut colour = world.ambient * m.ambient;
    // Origin for rays leaving on the viewer's side.
    let above = offset_origin::<R>(p, n);
    for light in &world.lights {
        let to_light = light.position - p;
        let dist = to_light.length();
        if !(dist > R::ZERO) {
            continue;
        }
        let l = to_light * (R::ONE / dist);
        let ndotl = ns.dot(l).max(R::ZERO);
        let h = l + v;
        let h_len = h.length();
        let ndoth = if h_len > R::ZERO { (ns.dot(h) / h_len).max(R::ZERO) } else { R::ZERO };
        let spec = if ndoth > m.specular_cos_min { ndoth.powf(m.shininess) } else { R::ZERO };
        let contrib = light.diffuse * m.diffuse * ndotl + light.specular * m.specular * spec;
        // A light that can add nothing needs no shadow ray.
        if contrib.max_element() <= R::ZERO {
            continue;
        }
        // Leave on the light's side of the surface.
        let origin = if n.dot(l) >= R::ZERO { above } else { offset_origin::<R>(p, -n) };
        rays.shadow += 1;
        let shadow = Ray::new(origin, l);
        if !world.occluded(&shadow, dist * (R::ONE - R::SHADOW_SHORTEN), id) {
            colour += contrib;
        }
    }

    if depth >= world.settings.max_depth {
        return colour;
    }
    let mut reflect_w = m.reflectivity;
    if m.transparency > R::ZERO {
        // Snell: eta = n1/n2; entering from outside goes 1 -> ior.
        let eta = if entering { R::ONE / m.ior } else { m.ior };
        let k = R::ONE - eta * eta * (R::ONE - cos_i * cos_i);
        if k < R::ZERO {
            reflect_w += m.transparency; // total internal reflection
        } else {
            let dir = (-v * eta + ns * (eta * cos_i - k.sqrt())).normalize();
            rays.refraction += 1;
            let refr = Ray::new(offset_origin::<R>(p, -n), dir);
            colour += trace(world, &refr, depth + 1, id, rays) * m.transparency;
        }
    }
    if reflect_w > R::ZERO {
        // R = 2(V.N)N - V
        let dir = (ns * (R::TWO * cos_i) - v).normalize();
        rays.reflection += 1;
        let refl = Ray::new(above, dir);
        colour += trace(world, &refl, depth + 1, id, rays) * reflect_w;
    }
    colour
}
