//! import geometry.wgsl
// Scene queries for worlds without a tree (world/query.rs: the loops over every
// sphere, then every plane). Compiled instead of bvh.wgsl, so scenes of a
// few spheres carry no traversal code.

fn closest_hit(o: vec3<f32>, d: vec3<f32>, skip: u32) -> Hit {
    return planes_closest(o, d, skip, spheres_closest(o, d, skip, Hit(BIG, NONE)));
}

fn occluded(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    return spheres_occlude(o, d, t_max, skip) || planes_occlude(o, d, t_max, skip);
}

fn surface(id: u32, p: vec3<f32>) -> SurfacePoint {
    return analytic_surface(id, p);
}

// Spheres and planes shade with their geometric normal.
fn shading_normal(id: u32, p: vec3<f32>, n: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    return n;
}
