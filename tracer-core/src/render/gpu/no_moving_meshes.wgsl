//! import distributed.wgsl
// The moving-mesh queries of distributed.wgsl for worlds without moving
// meshes: nothing to hit, so they add no work to the kernel. Compiled
// instead of moving_meshes.wgsl (which needs bvh.wgsl's traversal).

fn moving_meshes_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, tau: f32, h: Hit) -> Hit {
    return h;
}

fn moving_meshes_occluded(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32, tau: f32) -> bool {
    return false;
}

fn moving_mesh_of(id: u32) -> u32 {
    return NONE;
}

// Never called: moving_mesh_of finds no mesh.
fn moving_mesh_surface(k: u32, id: u32, q: vec3<f32>, v: vec3<f32>, tau: f32) -> Facing {
    return Facing(q, v, v, 0u, true);
}
