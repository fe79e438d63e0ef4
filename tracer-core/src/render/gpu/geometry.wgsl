//! import scene.wgsl
// The geometry tests of geometry.rs and the loops of world/query.rs over
// spheres and planes, written once for every driver and query module
// (bvh.wgsl holds the triangle test and the tree).

// geometry.rs Sphere::intersect: nearest t in (0, t_max) or MISS.
fn hit_sphere(s: Sphere, o: vec3<f32>, d: vec3<f32>, t_max: f32, from_surface: bool) -> f32 {
    let f = o - s.center;
    let b = dot(f, d);
    if (from_surface) {
        let t = -2.0 * b;
        return select(MISS, t, t > 0.0 && t < t_max);
    }
    let l = f - d * b;
    let ll = length(l);
    let r = s.radius;
    let disc = (r - ll) * (r + ll);
    if (!(disc >= 0.0)) {
        return MISS;
    }
    let c = dot(f, f) - r * r;
    let sq = sqrt(disc);
    let q = -b - select(sq, -sq, sign_bit(b));
    // q = 0 only for a ray tangent at its own origin: both roots are 0.
    if (q == 0.0) {
        return MISS;
    }
    let a = c / q;
    let t0 = select(q, a, a < q);
    let t1 = select(a, q, a < q);
    if (t0 > 0.0 && t0 < t_max) {
        return t0;
    }
    return select(MISS, t1, t1 > 0.0 && t1 < t_max);
}

// geometry.rs Plane::intersect.
fn hit_plane(p: Plane, o: vec3<f32>, d: vec3<f32>, t_max: f32, from_surface: bool) -> f32 {
    if (from_surface) {
        return MISS;
    }
    let denom = dot(p.normal, d);
    // Parallel: the CPU gets +-inf or NaN, which fail its test; WGSL
    // leaves x/0 undefined, so test it.
    if (denom == 0.0) {
        return MISS;
    }
    let t = (p.distance - dot(p.normal, o)) / denom;
    return select(MISS, t, t > 0.0 && t < t_max);
}

struct Hit {
    t: f32,
    id: u32,
}

// The scene queries `closest_hit`, `occluded`, `surface` and
// `shading_normal` come from analytic.wgsl (no tree: the loops below over
// every sphere and plane) or accel.wgsl (a tree over spheres and triangles
// traversed by bvh.wgsl, planes by loop), whichever the host compiles in.

// world/query.rs closest_hit, sphere part: strictly nearer than h.t wins.
fn spheres_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, h: Hit) -> Hit {
    var best = h;
    for (var i = 0u; i < N_SPHERES; i++) {
        let pid = (KIND_SPHERE << KIND_SHIFT) | i;
        let t = hit_sphere(spheres[i], o, d, best.t, pid == skip);
        if (t > 0.0) {
            best = Hit(t, pid);
        }
    }
    return best;
}

fn planes_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, h: Hit) -> Hit {
    var best = h;
    for (var i = 0u; i < N_PLANES; i++) {
        let pid = (KIND_PLANE << KIND_SHIFT) | i;
        let t = hit_plane(planes[i], o, d, best.t, pid == skip);
        if (t > 0.0) {
            best = Hit(t, pid);
        }
    }
    return best;
}

fn spheres_occlude(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    for (var i = 0u; i < N_SPHERES; i++) {
        let pid = (KIND_SPHERE << KIND_SHIFT) | i;
        if (hit_sphere(spheres[i], o, d, t_max, pid == skip) > 0.0) {
            return true;
        }
    }
    return false;
}

fn planes_occlude(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    for (var i = 0u; i < N_PLANES; i++) {
        let pid = (KIND_PLANE << KIND_SHIFT) | i;
        if (hit_plane(planes[i], o, d, t_max, pid == skip) > 0.0) {
            return true;
        }
    }
    return false;
}

// world/query.rs `surface`: a point snapped onto its primitive, the
// primitive's outward normal there, its material. (The viewer-facing
// `Surface` the shading step takes is shade.wgsl's.)
struct SurfacePoint {
    p: vec3<f32>,
    n: vec3<f32>,
    material: u32,
}

// The surface of sphere s at p (static spheres and distributed.wgsl's
// moving ones).
fn sphere_surface(s: Sphere, p: vec3<f32>) -> SurfacePoint {
    let d = p - s.center;
    let n = d * (1.0 / length(d));
    return SurfacePoint(s.center + n * s.radius, n, s.material);
}

// world/query.rs surface for spheres and planes.
fn analytic_surface(id: u32, p: vec3<f32>) -> SurfacePoint {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    if ((id >> KIND_SHIFT) == KIND_SPHERE) {
        return sphere_surface(spheres[index], p);
    }
    let pl = planes[index];
    let off = dot(pl.normal, p) - pl.distance;
    return SurfacePoint(p - pl.normal * off, pl.normal, pl.material);
}

// Ambient plus every unblocked light at surface point p (render/step.rs):
// n (the geometric normal) faces the viewer v, ns is the shading normal
// (n except on smooth triangles), `above` is p offset to the viewer's side,
