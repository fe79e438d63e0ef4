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

/// A world's triangles as the tree's build takes them: vertex positions,
/// each triangle's corners (indices into them) and shading record, and
/// the triangles themselves (gathered from their corners), or none.
pub(crate) struct TriangleArrays<'a, R: Real> {
    pub positions: &'a Vec<R::V3>,
    pub corners: &'a mut Vec<[u32; 3]>,
    pub shading: &'a mut Vec<TriangleShading>,
    /// Every triangle, or none: a big mesh of `f32` triangles alone (no
    /// spheres or instances) is built over its corners
    /// (`Bvh::build_indexed`), without boxes, and traversed without
    /// packets, its triangles read from their corners at each test.
    pub triangles: &'a mut Vec<Triangle<R>>,
}

/// The tree over `spheres`, `instances` (the boxes of a world's instanced
/// meshes as placed: `PrimId::INSTANCE` i for box i, the top level of
/// its two-level tree) and `tris` when the scene needs one (`force`:
/// always, never, or `None` for triangles, instances or at least
/// [`SPHERE_BVH_MIN`] spheres), else `None`. Reorders the triangles (their
/// corners, shading and the triangles themselves) to the tree's leaf
/// order, so a leaf's triangles are neighbours in memory, which the
/// tree's ids then follow.
pub(crate) fn build<R: Real>(
    spheres: &[Sphere<R>],
    instances: &[Aabb],
    tris: TriangleArrays<'_, R>,
    force: Option<bool>,
) -> Option<Bvh> {
    let n = tris.corners.len();
    let wanted = force.unwrap_or(n > 0 || !instances.is_empty() || spheres.len() >= SPHERE_BVH_MIN);
    if !wanted || (n == 0 && spheres.is_empty() && instances.is_empty()) {
        return None;
    }
    if n > 0 && tris.triangles.is_empty() {
        let positions: &dyn std::any::Any = tris.positions;
        let positions = positions
            .downcast_ref::<Vec<glam::Vec3A>>()
            .expect("only f32 triangles are built over their corners");
        assert!(
            spheres.is_empty() && instances.is_empty(),
            "a tree over corners holds triangles alone"
        );
        return Some(Bvh::build_indexed(positions, tris.corners, tris.shading));
    }
    assert_eq!(tris.triangles.len(), n, "every triangle, or none");
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
    let mut boxes = Vec::with_capacity(spheres.len() + instances.len() + n);
    for s in spheres {
        let c = s.center.to_array();
        let r = s.radius.to_f64();
        boxes.push(BuildBox::of(&Aabb::outward(
            c.map(|x| x - r),
            c.map(|x| x + r),
        )));
    }
    boxes.extend(instances.iter().map(BuildBox::of));
    for t in tris.triangles.iter() {
        let v = t.vertices();
        let lo = v[0].min(v[1]).min(v[2]).to_array();
        let hi = v[0].max(v[1]).max(v[2]).to_array();
        boxes.push(BuildBox::of(&Aabb::outward(lo, hi)));
    }
    // The boxes are partitioned in place (one array of them at the peak).
    let mut tree = Bvh::build_owned(boxes, &id);
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
        reorder(tris.triangles, tris.corners, tris.shading, src);
    }
    // The 4-wide triangle test (f32 only) wants the leaves' triangles packed.
    // Not with spheres: packing them too (NaN lanes sent to the sphere test)
    // made the bunny scene (a glass sphere in the tree) 9% slower.
    if spheres.is_empty() && instances.is_empty() {
        let any: &dyn std::any::Any = &*tris.triangles;
        if let Some(triangles) = any.downcast_ref::<Vec<Triangle<f32>>>() {
            tree.pack_triangles(triangles);
        }
    }
    Some(tree)
}

/// Puts `src[j]`'s triangle (its corners and shading too) at place j, in
/// place (cycle by cycle), without a second copy of the arrays; triangles
/// that no place takes (none, when every triangle is in the tree) are
/// dropped.
fn reorder<T: Copy, C: Copy, S: Copy>(
    triangles: &mut Vec<T>,
    corners: &mut Vec<C>,
    shading: &mut Vec<S>,
    mut src: Vec<u32>,
) {
    if src.len() != triangles.len() {
        *triangles = src.iter().map(|&i| triangles[i as usize]).collect();
        *corners = src.iter().map(|&i| corners[i as usize]).collect();
        *shading = src.iter().map(|&i| shading[i as usize]).collect();
        return;
    }
    for i in 0..src.len() {
        if src[i] as usize == i {
            continue;
        }
        let (t, c, s) = (triangles[i], corners[i], shading[i]);
        let mut j = i;
        loop {
            let k = src[j] as usize;
            src[j] = j as u32;
            if k == i {
                triangles[j] = t;
                corners[j] = c;
                shading[j] = s;
                break;
            }
            triangles[j] = triangles[k];
            corners[j] = corners[k];
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
        let (mut t, mut c, mut s): (Vec<u32>, Vec<i32>, Vec<u64>) = (
            (0..n).collect(),
            (0..n as i32).map(|x| -x).collect(),
            (0..n as u64).map(|x| x * 3).collect(),
        );
        super::reorder(&mut t, &mut c, &mut s, src.clone());
        assert_eq!(t, src);
        assert_eq!(c, src.iter().map(|&x| -(x as i32)).collect::<Vec<_>>());
        assert_eq!(s, src.iter().map(|&x| x as u64 * 3).collect::<Vec<_>>());
    }

    /// A big mesh's tree, built over its corners, is the tree its
    /// gathered triangles get (the same nodes), and both leave the
    /// corners and shading in the same leaf order; the gathered build's
    /// triangles are those corners' (100,000 random triangles over shared
    /// vertices).
    #[test]
    fn a_tree_over_corners_is_the_tree_over_triangles() {
        use crate::triangle::{TriangleShading, gather, gather_all};
        use glam::Vec3A;
        let mut seed = 7u64;
        let mut r = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let positions: Vec<Vec3A> = (0..60_000)
            .map(|_| Vec3A::new(r(), r(), r()) * 100.0)
            .collect();
        let mut pick = || (r() * 59_999.0) as u32;
        let corners: Vec<[u32; 3]> = (0..100_000).map(|_| [pick(), pick(), pick()]).collect();
        let shading: Vec<TriangleShading> = (0..corners.len() as u32)
            .map(|i| TriangleShading {
                material: i,
                attrs: 0,
            })
            .collect();
        let (mut c1, mut s1) = (corners.clone(), shading.clone());
        let mut gathered = gather_all::<f32>(&positions, &corners);
        let a = super::build::<f32>(
            &[],
            &[],
            super::TriangleArrays {
                positions: &positions,
                corners: &mut c1,
                shading: &mut s1,
                triangles: &mut gathered,
            },
            None,
        )
        .unwrap();
        let (mut c2, mut s2) = (corners.clone(), shading.clone());
        let b = super::build::<f32>(
            &[],
            &[],
            super::TriangleArrays {
                positions: &positions,
                corners: &mut c2,
                shading: &mut s2,
                triangles: &mut Vec::new(),
            },
            None,
        )
        .unwrap();
        assert!(a.nodes == b.nodes && a.prims == b.prims, "the same tree");
        assert!(c1 == c2 && s1 == s2, "the same leaf order");
        assert!(!a.packets.is_empty() && b.packets.is_empty());
        for (t, &c) in gathered.iter().zip(&c1) {
            assert_eq!(t.vertices(), gather::<f32>(&positions, c).vertices());
        }
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
