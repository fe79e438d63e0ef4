//! import scene.wgsl
//! import geometry.wgsl
//! import distributed.wgsl
//! import pbr.wgsl
// The shading step, once for every driver: what one ray sees and the rays
// it spawns (render/step.rs `Surface`, `Surface::light` and
// `add_secondary`; with distributed effects render/cpu/distributed.rs
// `light_term` and `shade`). The stack driver (whitted.wgsl `trace`) and
// the wavefront (wavefront.wgsl `wave_shade`) call `shade` and differ only
// in where the children go. Effects are pipeline overrides
// (distributed.wgsl: DISTRIBUTED, N_DLIGHTS, N_MOVING, ...; scene.wgsl:
// HAS_REFLECTION, HAS_REFRACTION, MAX_DEPTH): a Whitted scene's kernel
// compiles to the plain Whitted step.

// A ray still to trace: its contribution is weight * (colour it sees).
// `key` is its node key (distributed effects only).
struct Ray {
    origin: vec3<f32>,
    weight: f32,
    dir: vec3<f32>,
    depth: u32,
    skip: u32,
    key: u32,
}

// What shading needs of a hit (step.rs Surface): the point, the normals
// facing the viewer v, the material, the origin for rays leaving on the
// viewer's side.
struct Surface {
    id: u32,
    p: vec3<f32>,
    n: vec3<f32>,
    ns: vec3<f32>,
    v: vec3<f32>,
    entering: bool,
    cos_i: f32,
    material: u32,
    above: vec3<f32>,
}

// step.rs Surface::at: the hit of ray r, at the sample's time tau.
fn surface_at(r: Ray, hit: Hit, tau: f32) -> Surface {
    let v = -r.dir;
    let f = facing_at(hit.id, r.origin + r.dir * hit.t, v, tau);
    // Normal maps (pbr.wgsl; the shading normal as it is without them).
    let ns = normal_mapped(hit.id, f.p, f.material, f.n, f.ns, v);
    return Surface(hit.id, f.p, f.n, ns, v, f.entering, dot(ns, v), f.material, offset_origin(f.p, f.n));
}

// The term of a light at `pos` (step.rs `light_term`), its shadow ray
// included: zero when blocked or when it can add nothing (then no shadow
// ray). A term that is NaN is kept (and its shadow ray traced) when
// `nan_kept`, as the static Whitted step once did; the CPU's one step now
// drops it for every effect. Only an all-NaN term, which a validated
// scene cannot produce, tells the two apart.
fn light_term(sf: Surface, m: Material, pos: vec3<f32>, diffuse: vec3<f32>, specular: vec3<f32>, tau: f32, nan_kept: bool) -> vec3<f32> {
    let p = sf.p;
    let n = sf.n;
    let ns = sf.ns;
    let v = sf.v;
    let to_light = pos - p;
    let dist = length(to_light);
    if (!(dist > 0.0)) {
        return vec3<f32>(0.0);
    }
    let l = to_light * (1.0 / dist);
    let ndotl = max(dot(ns, l), 0.0);
    let h = l + v;
    let h_len = length(h);
    var ndoth = 0.0;
    if (h_len > 0.0) {
        ndoth = max(dot(ns, h) / h_len, 0.0);
    }
    var spec = 0.0;
    // Same cut-off as the CPU's f32 path: terms below 2^-24 are skipped.
    if (ndoth > m.specular_cos_min) {
        spec = pow(ndoth, m.shininess);
    }
    let contrib = diffuse * m.diffuse * ndotl + specular * m.specular * spec;
    // A light that can add nothing needs no shadow ray.
    let most = max(contrib.x, max(contrib.y, contrib.z));
    if (select(!(most > 0.0), most <= 0.0, nan_kept)) {
        return vec3<f32>(0.0);
    }
    // Leave on the light's side of the surface.
    var o = sf.above;
    if (dot(n, l) < 0.0) {
        o = offset_origin(p, -n);
    }
    tally[C_SHADOW] += 1u;
    if (occluded_through(o, l, dist * (1.0 - SHADOW_SHORTEN), sf.id, tau)) {
        return vec3<f32>(0.0);
    }
    return contrib;
}

// Ambient plus every light's term: the scene's point lights, or with
// distributed effects `dist`'s lights, area lights sampled at the ray's
// node key.
fn local_colour(sf: Surface, look: Looked, key: u32, seed: u32, s: u32, tau: f32) -> vec3<f32> {
    let m = look.m;
    var local = frame.ambient * m.ambient;
    if (HAS_PBR && look.emits) {
        local += look.emission;
    }
    if (!DISTRIBUTED) {
        for (var li = 0u; li < N_LIGHTS; li++) {
            let light = lights[li];
            local += light_term(sf, m, light.position, light.diffuse, light.specular, tau, true);
        }
        return local;
    }
    for (var li = 0u; li < N_DLIGHTS; li++) {
        let base = DIST_LIGHTS + 5u * li;
        let kind = bitcast<u32>(dist[base].w);
        let diffuse = dist[base + 3u].xyz;
        let specular = dist[base + 4u].xyz;
        if (kind == 0u) {
            local += light_term(sf, m, dist[base].xyz, diffuse, specular, tau, false);
            continue;
        }
        let count = bitcast<u32>(dist[base + 2u].w);
        let first = bitcast<u32>(dist[base + 3u].w);
        var sum = vec3<f32>(0.0);
        for (var i = 0u; i < count; i++) {
            let slot = SLOT_LIGHTS + 2u * (first + i);
            let u1 = uniform01(seed, s, node_dim(key, slot));
            let u2 = uniform01(seed, s, node_dim(key, slot + 1u));
            let y = light_point(li, stratified(i, count, u1, u2));
            sum += light_term(sf, m, y, diffuse, specular, tau, false);
        }
        local += sum * (1.0 / f32(count));
    }
    return local;
}

// What `shade` gives its driver: the colour the ray sees (to be weighted
// by its weight) and up to two children, refracted then reflected.
struct Shaded {
    colour: vec3<f32>,
    refracted: Ray,
    reflected: Ray,
    has_refracted: bool,
    has_reflected: bool,
}

// One ray of sample s of the pixel with `seed` at shutter fraction tau:
// background, or the local colour and the secondary rays (step.rs
// add_secondary; with cones, distributed.rs shade).
fn shade(r: Ray, seed: u32, s: u32, tau: f32) -> Shaded {
    var out: Shaded;
    out.has_refracted = false;
    out.has_reflected = false;
    let hit = closest_through(r.origin, r.dir, r.skip, tau);
    if (hit.id == NONE) {
        out.colour = frame.background;
        return out;
    }
    let sf = surface_at(r, hit, tau);
    let look = material_at(sf.id, sf.p, sf.material);
    let m = look.m;
    out.colour = local_colour(sf, look, r.key, seed, s, tau);
    if (r.depth >= MAX_DEPTH) {
        return out;
    }
    let p = sf.p;
    let n = sf.n;
    let ns = sf.ns;
    let v = sf.v;
    let cos_i = sf.cos_i;
    var reflect_w = m.reflectivity;
    if (HAS_REFRACTION && m.transparency > 0.0) {
        // Snell: eta = n1/n2; entering from outside goes 1 -> ior.
        let eta = select(m.ior, 1.0 / m.ior, sf.entering);
        let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
        if (k < 0.0) {
            reflect_w += m.transparency; // total internal reflection
        } else {
            var rdir = normalize(-v * eta + ns * (eta * cos_i - sqrt(k)));
            var below = true;
            if (DISTRIBUTED && m.translucency_cos < 1.0) {
                rdir = cone(rdir, m.translucency_cos,
                    uniform01(seed, s, node_dim(r.key, SLOT_TRANSLUCENCY)),
                    uniform01(seed, s, node_dim(r.key, SLOT_TRANSLUCENCY + 1u)));
                below = dot(rdir, n) < 0.0;
            }
            if (below) {
                tally[C_REFRACTION] += 1u;
                var key = 0u;
                if (DISTRIBUTED) {
                    key = child_key(r.key, 0u);
                }
                out.refracted = Ray(offset_origin(p, -n), r.weight * m.transparency, rdir, r.depth + 1u, sf.id, key);
                out.has_refracted = true;
            }
        }
    }
    if (HAS_REFLECTION && reflect_w > 0.0) {
        // R = 2(V.N)N - V
        var rdir = normalize(ns * (2.0 * cos_i) - v);
        var up = true;
        if (DISTRIBUTED && m.gloss_cos < 1.0) {
            rdir = cone(rdir, m.gloss_cos,
                uniform01(seed, s, node_dim(r.key, SLOT_GLOSS)),
                uniform01(seed, s, node_dim(r.key, SLOT_GLOSS + 1u)));
            up = dot(rdir, n) > 0.0;
        }
        if (up) {
            tally[C_REFLECTION] += 1u;
            var key = 0u;
            if (DISTRIBUTED) {
                key = child_key(r.key, 1u);
            }
            out.reflected = Ray(sf.above, r.weight * reflect_w, rdir, r.depth + 1u, sf.id, key);
            out.has_reflected = true;
        }
    }
    return out;
}
