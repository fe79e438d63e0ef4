//! A world's acceleration structure: whether a scene's spheres and
//! triangles get a tree, and building it (triangles reordered to the
//! tree's leaf order, packed for the `f32` 4-wide test).
//!
//! Dependencies go one way, `world` -> `accel` -> `bvh`: this module takes
//! the world's primitive arrays rather than the `World`, so that the world,
//! which stores the tree, builds it here and queries through it
//! (`world/query.rs`, where the world is the tree's `bvh::Primitives`
//! view), depends on it and not the other way round.

use crate::bvh::{Aabb, BuildBox, Bvh};
use crate::geometry::{PrimId, Sphere};
use crate::math::{Real, Vector3};
use crate::triangle::{Triangle, TriangleShading};

/// Scenes with fewer spheres than this and no triangles keep the plain loop
/// over spheres: a tree only adds box tests there. Measured with
/// `cargo run --release -p tracer-core --example accel_crossover` (2-core
/// machine, one thread, rays per CPU-second, the 4-wide `SpherePack` loop):
/// the loop wins up to 4 spheres (25 vs 23 M rays/s), ties at 6-8, loses
/// from 10 on (20 vs 23; 9 vs 21 at 64). Re-measure when either gets faster.
pub const SPHERE_BVH_MIN: usize = 10;

/// The tree over `spheres`, `instances` (the boxes of a world's instanced
/// meshes as placed: `PrimId::INSTANCE` i for box i, the top level of
/// its two-level tree) and `triangles` when the scene needs one
/// (`force`: always, never, or `None` for triangles, instances or at least
/// [`SPHERE_BVH_MIN`] spheres), else `None`. Reorders `triangles` and
/// their `shading` to the tree's leaf order (so a leaf's triangles are
/// neighbours in memory), which the tree's ids then follow. With
/// `give_up_triangles`, a tree of `f32` triangles alone takes them into its
/// packets and leaves `triangles` empty (`Bvh::triangle` reads one back):
/// a big mesh is then held once, not twice.
pub(crate) fn build<R: Real>(
    spheres: &[Sphere<R>],
    instances: &[Aabb],
    triangles: &mut Vec<Triangle<R>>,
    shading: &mut Vec<TriangleShading>,
    force: Option<bool>,
    give_up_triangles: bool,
) -> Option<Bvh> {
    let wanted = force.unwrap_or(
        !triangles.is_empty() || !instances.is_empty() || spheres.len() >= SPHERE_BVH_MIN,
    );
    if !wanted || (triangles.is_empty() && spheres.is_empty() && instances.is_empty()) {
        return None;
    }
    // Ids are spheres', then instances', then triangles', in that order.
    let (first_instance, first_triangle) = (
        spheres.len() as u32,
        (spheres.len() + instances.len()) as u32,
    );
    let id = |i: u32| {
        if i < first_instance {
            PrimId::new(PrimId::SPHERE, i)
        } else if i < first_triangle {
            PrimId::new(PrimId::INSTANCE, i - first_instance)
        } else {
            PrimId::new(PrimId::TRIANGLE, i - first_triangle)
        }
    };
    let mut boxes = Vec::with_capacity(spheres.len() + instances.len() + triangles.len());
    for s in spheres {
        let c = s.center.to_array();
        let r = s.radius.to_f64();
        boxes.push(BuildBox::of(&Aabb::outward(
            c.map(|x| x - r),
            c.map(|x| x + r),
        )));
    }
    boxes.extend(instances.iter().map(BuildBox::of));
    for t in triangles.iter() {
        let v = t.vertices();
        let lo = v[0].min(v[1]).min(v[2]).to_array();
        let hi = v[0].max(v[1]).max(v[2]).to_array();
        boxes.push(BuildBox::of(&Aabb::outward(lo, hi)));
    }
    // The boxes are partitioned in place (one array of them at the peak).
    let mut tree = Bvh::build_owned(boxes, &id);
    let n = triangles.len();
    if n > 0 {
        // src[j]: the triangle that goes to place j, in leaf order.
        let mut src = Vec::with_capacity(n);
        for id in tree
            .prims
            .iter_mut()
            .filter(|id| id.kind() == PrimId::TRIANGLE)
        {
            src.push(id.index() as u32);
            *id = PrimId::new(PrimId::TRIANGLE, src.len() as u32 - 1);
        }
        reorder(triangles, shading, src);
    }
    // The 4-wide triangle test (f32 only) wants the leaves' triangles packed.
    // Not with spheres: packing them too (NaN lanes sent to the sphere test)
    // made the bunny scene (a glass sphere in the tree) 9% slower.
    if spheres.is_empty() && instances.is_empty() {
        let any: &mut dyn std::any::Any = triangles;
        if let Some(tris) = any.downcast_mut::<Vec<Triangle<f32>>>() {
            if give_up_triangles {
                if let Err(back) = tree.pack_triangles_owned(std::mem::take(tris)) {
                    *tris = back;
                    tree.pack_triangles(tris);
                }
            } else {
                tree.pack_triangles(tris);
            }
        }
    }
    Some(tree)
}

/// Puts `src[j]`'s triangle (and shading) at place j, in place (cycle by
/// cycle), without a second copy of the arrays; triangles that no place
/// takes (none, when every triangle is in the tree) are dropped.
fn reorder<T: Copy, S: Copy>(triangles: &mut Vec<T>, shading: &mut Vec<S>, mut src: Vec<u32>) {
    if src.len() != triangles.len() {
        *triangles = src.iter().map(|&i| triangles[i as usize]).collect();
        *shading = src.iter().map(|&i| shading[i as usize]).collect();
        return;
    }
    for i in 0..src.len() {
        if src[i] as usize == i {
            continue;
        }
        let (t, s) = (triangles[i], shading[i]);
        let mut j = i;
        loop {
            let k = src[j] as usize;
            src[j] = j as u32;
            if k == i {
                triangles[j] = t;
                shading[j] = s;
                break;
            }
            triangles[j] = triangles[k];
            shading[j] = shading[k];
            j = k;
        }
    }
}

#[cfg(test)]
mod tests {
    /// The layering in the module docs, checked on the sources: neither the
    /// tree nor this module names the world.
    /// The in-place reordering equals gathering into new arrays.
    #[test]
    fn reorder_in_place_is_a_gather() {
        let n = 1000u32;
        let src: Vec<u32> = (0..n).map(|j| (j * 7919 + 13) % n).collect();
        let (mut t, mut s): (Vec<u32>, Vec<u64>) =
            ((0..n).collect(), (0..n as u64).map(|x| x * 3).collect());
        super::reorder(&mut t, &mut s, src.clone());
        assert_eq!(t, src);
        assert_eq!(s, src.iter().map(|&x| x as u64 * 3).collect::<Vec<_>>());
    }

    /// Triangles given up to the tree are its packets alone, which are
    /// those made from a kept copy, and read back bit for bit; with a
    /// sphere in the tree they stay where they were. 100,000 triangles:
    /// more than one chunk of the back-to-front packing.
    #[test]
    fn triangles_given_up_to_the_packets_read_back_exactly() {
        use crate::geometry::Sphere;
        use crate::triangle::{Triangle, TriangleShading};
        use glam::Vec3A;
        let mut seed = 7u64;
        let mut r = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let tris: Vec<Triangle<f32>> = (0..100_000)
            .map(|_| {
                let c = Vec3A::new(r(), r(), r()) * 100.0;
                Triangle::new([
                    c,
                    c + Vec3A::new(r(), 0.0, 0.1),
                    c + Vec3A::new(0.0, r(), r()),
                ])
            })
            .collect();
        let shading: Vec<TriangleShading> = (0..tris.len() as u32)
            .map(|i| TriangleShading {
                normals: crate::triangle::FLAT,
                material: i,
                attrs: 0,
            })
            .collect();
        let (mut kept, mut kept_s) = (tris.clone(), shading.clone());
        let a = super::build::<f32>(&[], &[], &mut kept, &mut kept_s, None, false).unwrap();
        let (mut given, mut given_s) = (tris.clone(), shading.clone());
        let b = super::build::<f32>(&[], &[], &mut given, &mut given_s, None, true).unwrap();
        assert!(given.is_empty() && kept.len() == tris.len());
        assert_eq!(given_s, kept_s);
        assert!(a.slots.is_empty() && b.slots.len() == tris.len());
        assert!(a.packets == b.packets, "the same packets");
        for (i, t) in kept.iter().enumerate() {
            let back = b.triangle(i).vertices();
            for (u, v) in back.iter().zip(t.vertices()) {
                assert_eq!(
                    u.to_array().map(f32::to_bits),
                    v.to_array().map(f32::to_bits)
                );
            }
        }
        let sphere = [Sphere::<f32> {
            center: Vec3A::ZERO,
            radius: 1.0,
            material: 0,
        }];
        let (mut with_sphere, mut s) = (tris.clone(), shading.clone());
        let c = super::build::<f32>(&sphere, &[], &mut with_sphere, &mut s, None, true).unwrap();
        assert!(with_sphere.len() == tris.len() && c.slots.is_empty() && c.packets.is_empty());
    }

    #[test]
    fn bvh_and_accel_do_not_depend_on_world() {
        let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut files = vec![src.join("accel.rs")];
        files.extend(
            std::fs::read_dir(src.join("bvh"))
                .unwrap()
                .map(|e| e.unwrap().path()),
        );
        assert!(files.len() >= 5, "{files:?}");
        for f in &files {
            let text = std::fs::read_to_string(f).unwrap();
            // The code, without comments and without tests (this one names the world).
            let code = text.split("#[cfg(test)]").next().unwrap();
            for line in code.lines().filter(|l| !l.trim_start().starts_with("//")) {
                assert!(
                    !line.contains("world::") && !line.contains("World"),
                    "{} names the world: {line}",
                    f.display()
                );
            }
        }
    }
}
