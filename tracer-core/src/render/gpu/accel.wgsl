//! import geometry.wgsl
//! import bvh.wgsl
// Scene queries for worlds with a BVH (world/query.rs): planes by loop, spheres,
// triangles and instances (instances.wgsl) through the tree, whose root is node 0. The host's
// choice for such worlds instead of analytic.wgsl.

// world/query.rs closest_hit_accel: planes by loop, then the tree.
fn closest_hit(o: vec3<f32>, d: vec3<f32>, skip: u32) -> Hit {
    let h = tree_closest(0u, o, d, skip, planes_closest(o, d, skip, Hit(BIG, NONE)));
    return resolve_instance(h, o, d, skip);
}

fn occluded(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    return planes_occlude(o, d, t_max, skip) || tree_occluded(0u, o, d, t_max, skip);
}

// world/query.rs surface; for triangles (triangle_surface there) the point
// snapped onto the triangle's plane and its outward geometric normal.
fn surface(id: u32, p: vec3<f32>) -> SurfacePoint {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    if ((id >> KIND_SHIFT) == KIND_TRIANGLE) {
        return triangle_surface(index, p);
    }
    if (HAS_INSTANCES && (id >> KIND_SHIFT) == KIND_INSTANCE_TRIANGLE) {
        return instance_surface(index, p);
    }
    return analytic_surface(id, p);
}

// world/query.rs shading_normal: spheres shade with their geometric normal.
fn shading_normal(id: u32, p: vec3<f32>, n: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    if ((id >> KIND_SHIFT) == KIND_TRIANGLE) {
        return triangle_shading_normal(index, p, n, v);
    }
    if (HAS_INSTANCES && (id >> KIND_SHIFT) == KIND_INSTANCE_TRIANGLE) {
        let t = placed_triangle(id, p);
        if (shading[t.tri].smooth_shaded == 0u) {
            return n;
        }
        return facing_normal(placed_normal_at(t), n, v);
    }
    return n;
}
