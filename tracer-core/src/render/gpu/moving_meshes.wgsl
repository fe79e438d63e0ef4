//! import distributed.wgsl
//! import bvh.wgsl
// Moving meshes on the GPU (distributed.rs `MovingMesh`; the mesh parts of
// render/cpu/distributed.rs `closest`, `occluded` and `surface`). Each mesh
// keeps its own tree, built at the shutter's opening, which lies in
// bvh.wgsl's arrays from node `root`; at shutter fraction tau the mesh has
// moved by tau * delta, so the ray enters its tree translated by the
// opposite. The host rebases every tree's triangle indices (layout.rs
// TreeData::pack), so a triangle's id names one triangle of one mesh: it
// is the hit's id and the skip id of rays leaving it, as is. Compiled in
// only for worlds with moving meshes.
//
// Keep in sync with layout.rs `DistData`: after the moving spheres, 3
// entries per mesh: (lo, root) (hi, first triangle) (delta, -), where
// [lo, hi] bounds the mesh's sweep over the shutter and its triangles are
// first triangle .. the next mesh's first (the last mesh's: to the end).

override N_MOVING_MESHES: u32 = 0u;

fn moving_mesh_base(k: u32) -> u32 {
    return DIST_LIGHTS + 5u * N_DLIGHTS + 2u * N_MOVING + 3u * k;
}

// distributed.rs ray_meets_box: whether the ray meets [lo, hi] before
// t_max. The box only culls, so its exit is widened (as bvh.wgsl's boxes).
fn meets_sweep(lo: vec3<f32>, hi: vec3<f32>, o: vec3<f32>, inv: vec3<f32>, t_max: f32) -> bool {
    // inv from reciprocal(): finite, so no 0 * inf and no NaN.
    let a = (lo - o) * inv;
    let b = (hi - o) * inv;
    let near = min(a, b);
    let far = max(a, b);
    let t0 = max(max(near.x, near.y), max(near.z, 0.0));
    let t1 = min(min(far.x, far.y), min(far.z, t_max));
    return t0 <= t1 * EXIT_WIDEN;
}

// Nearest hit on a moving mesh strictly nearer than h.t, else h.
fn moving_meshes_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, tau: f32, h: Hit) -> Hit {
    var best = h;
    let inv = reciprocal(d);
    for (var k = 0u; k < N_MOVING_MESHES; k++) {
        let base = moving_mesh_base(k);
        let lo = dist[base];
        if (meets_sweep(lo.xyz, dist[base + 1u].xyz, o, inv, best.t)) {
            best = tree_closest(bitcast<u32>(lo.w), o - dist[base + 2u].xyz * tau, d, skip, best);
        }
    }
    return best;
}

fn moving_meshes_occluded(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32, tau: f32) -> bool {
    let inv = reciprocal(d);
    for (var k = 0u; k < N_MOVING_MESHES; k++) {
        let base = moving_mesh_base(k);
        let lo = dist[base];
        if (meets_sweep(lo.xyz, dist[base + 1u].xyz, o, inv, t_max)
            && tree_occluded(bitcast<u32>(lo.w), o - dist[base + 2u].xyz * tau, d, t_max, skip)) {
            return true;
        }
    }
    return false;
}

// The moving mesh that primitive `id` belongs to, or NONE.
fn moving_mesh_of(id: u32) -> u32 {
    if ((id >> KIND_SHIFT) != KIND_TRIANGLE) {
        return NONE;
    }
    let index = id & ((1u << KIND_SHIFT) - 1u);
    var mesh = NONE;
    for (var k = 0u; k < N_MOVING_MESHES; k++) {
        if (index >= bitcast<u32>(dist[moving_mesh_base(k) + 1u].w)) {
            mesh = k;
        }
    }
    return mesh;
}

// distributed.rs surface of a hit at q on moving mesh k: the mesh's own
// surface at q moved back to the opening, then moved forward again.
fn moving_mesh_surface(k: u32, id: u32, q: vec3<f32>, v: vec3<f32>, tau: f32) -> Facing {
    let off = dist[moving_mesh_base(k) + 2u].xyz * tau;
    let index = id & ((1u << KIND_SHIFT) - 1u);
    let sf = triangle_surface(index, q - off);
    let entering = dot(sf.n, v) >= 0.0;
    let n = select(-sf.n, sf.n, entering);
    let ns = triangle_shading_normal(index, sf.p, n, v);
    return Facing(sf.p + off, n, ns, sf.material, entering);
}
