//! import scene.wgsl
//! import bvh.wgsl
//! import distributed.wgsl
// Model files' materials on the GPU, written once for every driver: the
// mirror of render/step.rs `material_at` (material.rs `Pbr::at`,
// `Pbr::whitted`, `base_color_at`, `cut_away`), texture.rs
// `TextureRef::sample` (the same bilinear filter, wraps, transform and
// decode tables, so the same f32 arithmetic) and world/query.rs
// `attrs_at` and `through_cutouts`. Compiled into every scene kernel;
// scenes without model materials leave HAS_PBR and HAS_CUTOUTS off and
// run the step as before.

// ---- Layouts: keep in sync with layout.rs (GpuTexRef, GpuPbr, GpuVertexAttr)
struct TexRef {
    offset: u32,
    width: u32,
    height: u32,
    flags: u32,
    row0: vec3<f32>,
    mips: u32,
    row1: vec3<f32>,
    levels: u32,
}

struct Pbr {
    base_color: vec4<f32>,
    emissive: vec3<f32>,
    flags: u32,
    metallic: f32,
    roughness: f32,
    transmission: f32,
    ior: f32,
    f0: vec3<f32>,
    alpha_cutoff: f32,
    occlusion_strength: f32,
    normal_scale: f32,
    bump_scale: f32,
    pad: f32,
    tex: array<TexRef, 6>,
}

struct VertexAttr {
    uv0: vec2<f32>,
    uv1: vec2<f32>,
    colour: vec4<f32>,
    tangent: vec4<f32>,
}

// Bindings mat_pbr, pbrs, tri_attrs, vertex_attrs, texels: wgsl.rs SCENE.

// layout.rs TEX_* and PBR_*.
const TEX_PRESENT: u32 = 1u;
const TEX_NEAREST: u32 = 2u;
const TEX_SRGB: u32 = 4u;
const TEX_UV1: u32 = 8u;
const TEX_WRAP_SHIFT: u32 = 4u;
const PBR_MASK: u32 = 1u;
const PBR_BLEND: u32 = 2u;
const PBR_MTL: u32 = 4u;
const PBR_VARIES: u32 = 8u;
const PBR_CULL: u32 = 16u;
const PBR_BUMP: u32 = 32u;
const T_BASE: u32 = 0u;
const T_MR: u32 = 1u;
const T_EMISSIVE: u32 = 2u;
const T_OCCLUSION: u32 = 3u;
const T_ALPHA: u32 = 4u;
const T_NORMAL: u32 = 5u;
// texels[0..256]: sRGB byte -> linear; [256..512]: byte / 255.
const TABLE_LINEAR: u32 = 256u;
// world/query.rs MAX_CUTOUT_LAYERS.
const MAX_CUTOUT_LAYERS: u32 = 64u;
// math.rs SPECULAR_FLOOR of f32 (2^-24).
const SPECULAR_FLOOR_F32: f32 = 5.9604645e-8;

override HAS_PBR: bool = false;
override HAS_CUTOUTS: bool = false;

fn is_finite_f32(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// texture.rs wrap_index: integer coordinate i in a side of n texels.
fn wrap_index(i: i32, n: u32, mode: u32) -> u32 {
    let m = i32(n);
    if (mode == 1u) {
        return u32(clamp(i, 0, m - 1));
    }
    if (mode == 2u) {
        var k = i % (2 * m);
        k = select(k, k + 2 * m, k < 0);
        return u32(select(2 * m - 1 - k, k, k < m));
    }
    var k = i % m;
    k = select(k, k + m, k < 0);
    return u32(k);
}

// texture.rs TextureRef::texel: one texel of the level at word `offset`,
// `width` texels wide, decoded to linear values.
fn texel(t: TexRef, offset: u32, width: u32, x: u32, y: u32) -> vec4<f32> {
    let w = texels[offset + y * width + x];
    let b = vec4<u32>(w & 255u, (w >> 8u) & 255u, (w >> 16u) & 255u, w >> 24u);
    let colour = select(vec3<u32>(TABLE_LINEAR), vec3<u32>(0u), (t.flags & TEX_SRGB) != 0u);
    return vec4<f32>(
        bitcast<f32>(texels[colour.x + b.x]),
        bitcast<f32>(texels[colour.y + b.y]),
        bitcast<f32>(texels[colour.z + b.z]),
        bitcast<f32>(texels[TABLE_LINEAR + b.w]));
}

// One mip level of a texture: its first word and size.
struct TexLevel {
    offset: u32,
    width: u32,
    height: u32,
}

// texture.rs TextureRef::filter: bilinear (or nearest) over one level at
// texture coordinate uv (before the transform, which is applied here).
fn tex_filter(t: TexRef, l: TexLevel, nearest: bool, uv: vec2<f32>) -> vec4<f32> {
    let u = t.row0.x * uv.x + t.row0.y * uv.y + t.row0.z;
    let v = t.row1.x * uv.x + t.row1.y * uv.y + t.row1.z;
    let ws = (t.flags >> TEX_WRAP_SHIFT) & 3u;
    let wt = (t.flags >> (TEX_WRAP_SHIFT + 2u)) & 3u;
    var fx = 0.5;
    if (is_finite_f32(u)) {
        fx = u * f32(l.width);
    }
    var fy = 0.5;
    if (is_finite_f32(v)) {
        fy = v * f32(l.height);
    }
    fx = clamp(fx, -1e9, 1e9);
    fy = clamp(fy, -1e9, 1e9);
    if (nearest) {
        return texel(t, l.offset, l.width, wrap_index(i32(floor(fx)), l.width, ws), wrap_index(i32(floor(fy)), l.height, wt));
    }
    let x = fx - 0.5;
    let y = fy - 0.5;
    let x0 = floor(x);
    let y0 = floor(y);
    let tx = x - x0;
    let ty = y - y0;
    let xi = i32(x0);
    let yi = i32(y0);
    let xa = wrap_index(xi, l.width, ws);
    let xb = wrap_index(xi + 1, l.width, ws);
    let ya = wrap_index(yi, l.height, wt);
    let yb = wrap_index(yi + 1, l.height, wt);
    let a = texel(t, l.offset, l.width, xa, ya);
    let b = texel(t, l.offset, l.width, xb, ya);
    let c = texel(t, l.offset, l.width, xa, yb);
    let d = texel(t, l.offset, l.width, xb, yb);
    let top = a + (b - a) * tx;
    let bottom = c + (d - c) * tx;
    return top + (bottom - top) * ty;
}

// Level k of texture t (0: the image; texture.rs Image::levels: each side
// half the last, rounded down, at least 1, one level after another).
fn tex_level(t: TexRef, k: u32) -> TexLevel {
    if (k == 0u) {
        return TexLevel(t.offset, t.width, t.height);
    }
    var l = TexLevel(t.mips, max(t.width / 2u, 1u), max(t.height / 2u, 1u));
    for (var i = 1u; i < k; i++) {
        l.offset += l.width * l.height;
        l.width = max(l.width / 2u, 1u);
        l.height = max(l.height / 2u, 1u);
    }
    return l;
}

// texture.rs TextureRef::sample: the full-resolution image at uv.
fn tex_sample_uv(t: TexRef, uv: vec2<f32>) -> vec4<f32> {
    return tex_filter(t, tex_level(t, 0u), (t.flags & TEX_NEAREST) != 0u, uv);
}

// texture.rs TextureRef::sample_at: trilinear at the hit's texture
// coordinates (its UV set) and level of detail.
fn tex_sample(t: TexRef, at: Attrs) -> vec4<f32> {
    let set1 = (t.flags & TEX_UV1) != 0u;
    let uv = select(at.uv0, at.uv1, set1);
    let det = abs(t.row0.x * t.row1.y - t.row0.y * t.row1.x);
    let offset = 0.5 * log2(det * f32(t.width) * f32(t.height));
    var lod = select(at.lod.x, at.lod.y, set1) + offset;
    if (!(lod > 0.0)) {
        return tex_sample_uv(t, uv);
    }
    lod = min(lod, f32(t.levels));
    let k = floor(lod);
    let frac = lod - k;
    let a = tex_filter(t, tex_level(t, u32(k)), false, uv);
    if (frac == 0.0 || u32(k) == t.levels) {
        return a;
    }
    let b = tex_filter(t, tex_level(t, u32(k) + 1u), false, uv);
    return a + (b - a) * frac;
}

// texture.rs SurfaceAttrs: texture coordinates, vertex colour and the
// footprint's level of detail per set at a point of a triangle; zeros,
// white and no footprint for a triangle without them.
struct Attrs {
    uv0: vec2<f32>,
    uv1: vec2<f32>,
    colour: vec4<f32>,
    lod: vec2<f32>,
}

// SurfaceAttrs::NONE: no texture coordinates, white, no footprint.
fn no_attrs() -> Attrs {
    return Attrs(vec2<f32>(0.0), vec2<f32>(0.0), vec4<f32>(1.0), vec2<f32>(-BIG));
}

// world/query.rs attrs_at: at p on triangle id (a world triangle or an
// instance's).
fn attrs_at(id: u32, p: vec3<f32>) -> Attrs {
    let t = placed_triangle(id, p);
    if (t.tri == NONE) {
        return no_attrs();
    }
    let a = shading[t.tri].attrs;
    if (a == NONE) {
        return no_attrs();
    }
    let va = vertex_attrs[tri_attrs[3u * a]];
    let vb = vertex_attrs[tri_attrs[3u * a + 1u]];
    let vc = vertex_attrs[tri_attrs[3u * a + 2u]];
    let b = triangle_barycentric(t.tri, t.q);
    return Attrs(
        va.uv0 * b.x + vb.uv0 * b.y + vc.uv0 * b.z,
        va.uv1 * b.x + vb.uv1 * b.y + vc.uv1 * b.z,
        va.colour * b.x + vb.colour * b.y + vc.colour * b.z,
        texture_lod(placed_corners(t), p, va, vb, vc));
}

// world/query.rs texture_lod: log2 of the side of the camera's pixel
// footprint at p, on the triangle of world-space corners `tri`, in each
// UV set's texture coordinates (-BIG: none).
fn texture_lod(tri: Triangle, p: vec3<f32>, va: VertexAttr, vb: VertexAttr, vc: VertexAttr) -> vec2<f32> {
    let c = cross(tri.v1 - tri.v0, tri.v2 - tri.v0);
    let area = length(c);
    let dist = length(p);
    var cosine = abs(dot(c, p) / (area * dist));
    if (!(cosine >= 1e-4)) {
        cosine = 1e-4;
    }
    let spread = 2.0 * length(frame.up) * frame.inv_height;
    let per_sample = max(1.0 / f32(max(frame.samples, 1u)), 1.0 / 64.0);
    let foot = spread * spread * dist * dist / cosine * per_sample;
    let d0 = vb.uv0 - va.uv0;
    let e0 = vc.uv0 - va.uv0;
    let d1 = vb.uv1 - va.uv1;
    let e1 = vc.uv1 - va.uv1;
    let uv_area = abs(vec2<f32>(d0.x * e0.y - e0.x * d0.y, d1.x * e1.y - e1.x * d1.y));
    let lod = 0.5 * log2(foot * uv_area / area);
    // NaN (0/0) and -inf read the image itself, as -BIG does.
    return select(vec2<f32>(-BIG), lod, lod > vec2<f32>(-BIG));
}

// material.rs Pbr::base_color_at: factor x texture x vertex colour, alpha
// times the MTL alpha map.
fn base_color_at(p: Pbr, at: Attrs) -> vec4<f32> {
    var t = vec4<f32>(1.0);
    if ((p.tex[T_BASE].flags & TEX_PRESENT) != 0u) {
        t = tex_sample(p.tex[T_BASE], at);
    }
    var c = p.base_color * t * at.colour;
    if ((p.tex[T_ALPHA].flags & TEX_PRESENT) != 0u) {
        let s = tex_sample(p.tex[T_ALPHA], at);
        c.w = c.w * (s.x * s.w);
    }
    return c;
}

// world/query.rs cut_away: whether the point p of primitive id, met along
// d, is cut away (a MASK material's alpha there below its cutoff, or d
// meets the back face of a single-sided surface).
fn cut_away(id: u32, p: vec3<f32>, d: vec3<f32>) -> bool {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    var material: u32;
    var normal: vec3<f32>;
    if ((id >> KIND_SHIFT) == KIND_TRIANGLE) {
        material = shading[index].material;
        normal = shading[index].normal;
    } else if (HAS_INSTANCES && (id >> KIND_SHIFT) == KIND_INSTANCE_TRIANGLE) {
        let sp = instance_surface(index, p);
        material = sp.material;
        normal = sp.n;
    } else {
        return false;
    }
    let pi = mat_pbr[material];
    if (pi == NONE) {
        return false;
    }
    let pb = pbrs[pi];
    if ((pb.flags & PBR_CULL) != 0u && dot(normal, d) > 0.0) {
        return true;
    }
    if ((pb.flags & PBR_MASK) == 0u) {
        return false;
    }
    return base_color_at(pb, attrs_at(id, p)).w < pb.alpha_cutoff;
}

// world/query.rs closest_hit with cut-outs (through_cutouts): each cut-out
// hit is left by a ray from it along the same direction, at most
// MAX_CUTOUT_LAYERS of them (past that the surface counts as hit).
fn closest_through(o: vec3<f32>, d: vec3<f32>, skip: u32, tau: f32) -> Hit {
    var h = closest_at(o, d, skip, tau);
    if (!HAS_CUTOUTS) {
        return h;
    }
    var t0 = 0.0;
    for (var i = 0u; i < MAX_CUTOUT_LAYERS; i++) {
        if (h.id == NONE) {
            return h;
        }
        let p = o + d * (t0 + h.t);
        if (!cut_away(h.id, p, d)) {
            return Hit(t0 + h.t, h.id);
        }
        t0 += h.t;
        h = closest_at(p, d, h.id, tau);
    }
    if (h.id != NONE) {
        h.t = t0 + h.t;
    }
    return h;
}

// world/query.rs occluded: whether anything but cut-outs lies on the ray before t_max.
fn occluded_through(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32, tau: f32) -> bool {
    if (!HAS_CUTOUTS) {
        return occluded_at(o, d, t_max, skip, tau);
    }
    let h = closest_through(o, d, skip, tau);
    return h.id != NONE && h.t < t_max;
}

// A hit's material (render/step.rs material_at) and its emission, added
// to the ambient term where `emits` (step.rs Surface::ambient: model
// materials only).
struct Looked {
    m: Material,
    emission: vec3<f32>,
    emits: bool,
}

// The model material (pbrs index) of a hit on primitive id with material
// index `material`, NONE where there is none to look up.
fn pbr_index(id: u32, material: u32) -> u32 {
    let kind = id >> KIND_SHIFT;
    if (!HAS_PBR || (kind != KIND_TRIANGLE && kind != KIND_INSTANCE_TRIANGLE)) {
        return NONE;
    }
    return mat_pbr[material];
}

// What a model material's textures and vertex colours make of it at the
// point p of primitive id (material.rs `Pbr::at`, the textures sampled
// once): the base colour, emission, metallic and roughness, and the
// ambient term's occlusion factor. The one lookup both integrators take
// their parameters from: Whitted's material (material_at) and the path
// integrator's BSDF (path.wgsl `bsdf_at`).
struct PbrAt {
    base: vec4<f32>,
    emission: vec3<f32>,
    metallic: f32,
    roughness: f32,
    occlusion: f32,
}

fn pbr_at(pb: Pbr, id: u32, p: vec3<f32>) -> PbrAt {
    let at = attrs_at(id, p);
    var out = PbrAt(base_color_at(pb, at), pb.emissive, pb.metallic, pb.roughness, 1.0);
    if ((pb.tex[T_EMISSIVE].flags & TEX_PRESENT) != 0u) {
        out.emission = pb.emissive * tex_sample(pb.tex[T_EMISSIVE], at).xyz;
    }
    if ((pb.flags & PBR_MTL) != 0u) {
        return out;
    }
    if ((pb.tex[T_MR].flags & TEX_PRESENT) != 0u) {
        let s = tex_sample(pb.tex[T_MR], at);
        out.roughness = out.roughness * s.y;
        out.metallic = out.metallic * s.z;
    }
    if ((pb.tex[T_OCCLUSION].flags & TEX_PRESENT) != 0u) {
        let o = tex_sample(pb.tex[T_OCCLUSION], at).x;
        out.occlusion = 1.0 + pb.occlusion_strength * (o - 1.0);
    }
    return out;
}

fn material_at(id: u32, p: vec3<f32>, material: u32) -> Looked {
    let m = materials[material];
    let pi = pbr_index(id, material);
    if (pi == NONE) {
        return Looked(m, vec3<f32>(0.0), false);
    }
    let pb = pbrs[pi];
    if ((pb.flags & PBR_VARIES) == 0u) {
        return Looked(m, pb.emissive, true);
    }
    let at = pbr_at(pb, id, p);
    let base = at.base;
    let emission = at.emission;
    if ((pb.flags & PBR_MTL) != 0u) {
        var out = m;
        out.ambient = m.ambient * base.xyz;
        out.diffuse = m.diffuse * base.xyz;
        return Looked(out, emission, true);
    }
    // material.rs Pbr::whitted, then Material::from_desc.
    let metallic = clamp(at.metallic, 0.0, 1.0);
    let rough = clamp(at.roughness, 0.0, 1.0);
    let reflectivity = metallic * (1.0 - rough) * (1.0 - rough);
    let transmission = clamp(pb.transmission, 0.0, 1.0) * (1.0 - metallic);
    let diffuse = base.xyz * (1.0 - reflectivity) * (1.0 - transmission);
    var blend = 0.0;
    if ((pb.flags & PBR_BLEND) != 0u) {
        blend = clamp(1.0 - base.w, 0.0, 1.0);
    }
    let r = max(rough, 0.05);
    let r2 = r * r;
    let shininess = max(2.0 / (r2 * r2) - 2.0, 1.0);
    var ambient = diffuse;
    if ((pb.tex[T_OCCLUSION].flags & TEX_PRESENT) != 0u) {
        ambient = diffuse * at.occlusion;
    }
    let out = Material(
        ambient,
        shininess,
        diffuse,
        reflectivity,
        pb.f0 + (base.xyz - pb.f0) * metallic,
        max(blend, transmission),
        pb.ior,
        pow(SPECULAR_FLOOR_F32, 1.0 / shininess),
        1.0,
        1.0);
    return Looked(out, emission, true);
}

// render/step.rs shading_normal: `ns` (the shading normal facing the
// viewer) tilted by a model material's normalTexture, in the frame of the
// interpolated vertex normal, the tangent made orthogonal to it and
// w N x T; reversed on a back face; ns where the tilted normal would face
// away from the viewer v. n: the geometric normal facing the viewer.
fn normal_mapped(id: u32, p: vec3<f32>, material: u32, n: vec3<f32>, ns: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    let pi = pbr_index(id, material);
    if (pi == NONE) {
        return ns;
    }
    let pb = pbrs[pi];
    if ((pb.tex[T_NORMAL].flags & TEX_PRESENT) == 0u) {
        return ns;
    }
    // world/query.rs tangent_at.
    let placed = placed_triangle(id, p);
    if (placed.tri == NONE) {
        return ns;
    }
    let a = shading[placed.tri].attrs;
    if (a == NONE) {
        return ns;
    }
    let va = vertex_attrs[tri_attrs[3u * a]];
    let vb = vertex_attrs[tri_attrs[3u * a + 1u]];
    let vc = vertex_attrs[tri_attrs[3u * a + 2u]];
    let normal = placed_normal_at(placed);
    var tilted0: vec3<f32>;
    if ((pb.flags & PBR_BUMP) != 0u) {
        let bumped = bumped_normal(pb, id, placed, p, va, vb, vc, normal);
        if (!bumped.ok) {
            return ns;
        }
        tilted0 = bumped.n;
    } else {
        if (va.tangent.w == 0.0 || vb.tangent.w == 0.0 || vc.tangent.w == 0.0) {
            return ns;
        }
        let b = triangle_barycentric(placed.tri, placed.q);
        let tw = placed_tangent(placed, vec4<f32>(va.tangent.xyz * b.x + vb.tangent.xyz * b.y + vc.tangent.xyz * b.z, va.tangent.w));
        let t = tw.xyz;
        let at = attrs_at(id, p);
        let c = tex_sample(pb.tex[T_NORMAL], at);
        let local = vec3<f32>(
            (2.0 * c.x - 1.0) * pb.normal_scale,
            (2.0 * c.y - 1.0) * pb.normal_scale,
            2.0 * c.z - 1.0);
        let along0 = t - normal * dot(normal, t);
        let len0 = length(along0);
        if (!(len0 > 0.0 && len0 <= BIG)) {
            return ns;
        }
        let along = along0 * (1.0 / len0);
        let across = cross(normal, along) * select(1.0, -1.0, tw.w < 0.0);
        tilted0 = along * local.x + across * local.y + normal * local.z;
    }
    let len = length(tilted0);
    if (!(len > 0.0 && len <= BIG)) {
        return ns;
    }
    var tilted = tilted0 * (1.0 / len);
    if (dot(normal, n) < 0.0) {
        tilted = -tilted;
    }
    return select(ns, tilted, dot(tilted, v) > 0.0);
}

struct Bumped {
    n: vec3<f32>,
    ok: bool,
}

// render/step.rs bumped_normal: the normal (not unit) of triangle id's
// surface (`placed` at p) displaced along its unit normal by bump_scale x
// the bump map (the normal slot, first channel) at p, turned to the
// normal's side; ok false where its texture coordinates span no area.
fn bumped_normal(pb: Pbr, id: u32, placed: Placed, p: vec3<f32>, va: VertexAttr, vb: VertexAttr, vc: VertexAttr, normal: vec3<f32>) -> Bumped {
    let t = pb.tex[T_NORMAL];
    let set1 = (t.flags & TEX_UV1) != 0u;
    let ua = select(va.uv0, va.uv1, set1);
    let ub = select(vb.uv0, vb.uv1, set1);
    let uc = select(vc.uv0, vc.uv1, set1);
    let tri = placed_corners(placed);
    let e1 = tri.v1 - tri.v0;
    let e2 = tri.v2 - tri.v0;
    let d1 = ub - ua;
    let d2 = uc - ua;
    let det = d1.x * d2.y - d2.x * d1.y;
    if (!(det != 0.0 && abs(det) <= BIG)) {
        return Bumped(normal, false);
    }
    let inv = 1.0 / det;
    let dpdu = (e1 * d2.y - e2 * d1.y) * inv;
    let dpdv = (e2 * d1.x - e1 * d2.x) * inv;
    let at = attrs_at(id, p);
    let uv = select(at.uv0, at.uv1, set1);
    let du = 1.0 / f32(t.width);
    let dv = 1.0 / f32(t.height);
    let hu = (height_at(t, uv + vec2<f32>(du, 0.0)) - height_at(t, uv - vec2<f32>(du, 0.0))) / (2.0 * du);
    let hv = (height_at(t, uv + vec2<f32>(0.0, dv)) - height_at(t, uv - vec2<f32>(0.0, dv))) / (2.0 * dv);
    let pu = dpdu + normal * (hu * pb.bump_scale);
    let pv = dpdv + normal * (hv * pb.bump_scale);
    let b = cross(pu, pv);
    return Bumped(select(b, -b, dot(b, normal) < 0.0), true);
}

// A bump map's height (first channel) at uv (of its own set).
fn height_at(t: TexRef, uv: vec2<f32>) -> f32 {
    return tex_sample_uv(t, uv).x;
}
