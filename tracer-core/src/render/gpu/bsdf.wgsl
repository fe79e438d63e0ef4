//! import scene.wgsl
// The path integrator's BSDF on the GPU: the mirror of bsdf.rs (glTF
// metallic-roughness with KHR_materials_specular/ior/transmission, a
// mirror layer for the thesis's reflectivity, delta lobes below
// DELTA_ALPHA). Keep in sync with bsdf.rs: same lobes, same order of
// choices, same numbers drawn. Directions are in the shading frame (z
// along the shading normal on the viewer's side); wo to the viewer.

const BSDF_PI: f32 = 3.14159265358979;
const BSDF_INV_PI: f32 = 0.318309886183791;
const BSDF_TWO_PI: f32 = 6.28318530717959;
// bsdf.rs DELTA_ALPHA.
const DELTA_ALPHA: f32 = 1.0e-3;

// layout.rs `PathData`'s per-material words, unpacked.
struct Bsdf {
    base: vec3<f32>,
    metallic: f32,
    spec_colour: vec3<f32>,
    roughness: f32,
    emission: vec3<f32>,
    ior: f32,
    transmission: f32,
    specular: f32,
    mirror: f32,
    // bsdf.rs `absorption`: the volume inside, per unit of distance.
    absorption: vec3<f32>,
}

struct BsdfSample {
    wi: vec3<f32>,
    weight: vec3<f32>,
    pdf: f32,
    delta: bool,
    // false: the path ends (bsdf.rs `sample` returned None).
    ok: bool,
}

struct Lobes {
    spec: f32,
    diff: f32,
    trans: f32,
}

fn bsdf_lum(c: vec3<f32>) -> f32 {
    return (c.x + c.y + c.z) * (1.0 / 3.0);
}

fn bsdf_max3(c: vec3<f32>) -> f32 {
    return max(c.x, max(c.y, c.z));
}

fn pow5(x: f32) -> f32 {
    let x2 = x * x;
    return x2 * x2 * x;
}

fn bsdf_alpha(b: Bsdf) -> f32 {
    return b.roughness * b.roughness;
}

fn bsdf_is_delta(b: Bsdf) -> bool {
    return bsdf_alpha(b) < DELTA_ALPHA;
}

// bsdf.rs `is_lambert`: the Lambert lobe is all there is.
fn bsdf_is_lambert(b: Bsdf) -> bool {
    return b.specular == 0.0 && b.metallic == 0.0 && b.mirror == 0.0 && b.transmission == 0.0;
}

fn has_smooth_lobe(b: Bsdf) -> bool {
    let diffuse = (1.0 - b.mirror) * (1.0 - b.metallic) * (1.0 - b.transmission) * bsdf_max3(b.base);
    return diffuse > 0.0 || !bsdf_is_delta(b);
}

fn f_dielectric(b: Bsdf, cos: f32, eta: f32) -> vec3<f32> {
    var f0 = (b.ior - 1.0) / (b.ior + 1.0);
    f0 = f0 * f0;
    let f0c = min(b.spec_colour * f0, vec3<f32>(1.0)) * b.specular;
    let f90 = vec3<f32>(b.specular);
    var c = cos;
    if (eta < 1.0) {
        let sin2_t = (1.0 - cos * cos) / (eta * eta);
        if (sin2_t >= 1.0) {
            return f90;
        }
        c = sqrt(1.0 - sin2_t);
    }
    return f0c + (f90 - f0c) * pow5(1.0 - min(max(c, 0.0), 1.0));
}

fn f_metal(b: Bsdf, cos: f32) -> vec3<f32> {
    return b.base + (vec3<f32>(1.0) - b.base) * pow5(1.0 - min(max(cos, 0.0), 1.0));
}

fn f_reflect(b: Bsdf, cos: f32, eta: f32) -> vec3<f32> {
    let f = f_dielectric(b, cos, eta) * (1.0 - b.metallic) + f_metal(b, cos) * b.metallic;
    return vec3<f32>(b.mirror) + f * (1.0 - b.mirror);
}

fn bsdf_lobes(b: Bsdf, cos_o: f32, eta: f32) -> Lobes {
    let fd = f_dielectric(b, cos_o, eta);
    let keep = 1.0 - b.mirror;
    let spec = bsdf_lum(f_reflect(b, cos_o, eta));
    let dielectric = keep * (1.0 - b.metallic) * (1.0 - bsdf_max3(fd)) * bsdf_lum(b.base);
    let diff = dielectric * (1.0 - b.transmission);
    let trans = dielectric * b.transmission;
    let sum = spec + diff + trans;
    if (!(sum > 0.0)) {
        return Lobes(0.0, 0.0, 0.0);
    }
    let k = 1.0 / sum;
    return Lobes(spec * k, diff * k, trans * k);
}

fn ggx_d(c: f32, a: f32) -> f32 {
    let a2 = a * a;
    let k = c * c * (a2 - 1.0) + 1.0;
    return a2 / (BSDF_PI * k * k);
}

fn smith_g1(c: f32, a: f32) -> f32 {
    let a2 = a * a;
    return 2.0 * c / (c + sqrt(a2 + (1.0 - a2) * c * c));
}

fn smith_v(co: f32, ci: f32, a: f32) -> f32 {
    let a2 = a * a;
    let gv = ci * sqrt(co * co * (1.0 - a2) + a2);
    let gl = co * sqrt(ci * ci * (1.0 - a2) + a2);
    let s = gv + gl;
    if (s > 0.0) {
        return 0.5 / s;
    }
    return 0.0;
}

// f(wo, wi) cos(wi) of the non-delta reflection lobes (xyz) and the
// mixture's pdf of sampling wi (w): bsdf.rs `eval`.
fn bsdf_eval(b: Bsdf, wo: vec3<f32>, wi: vec3<f32>, eta: f32) -> vec4<f32> {
    let co = wo.z;
    let ci = wi.z;
    if (!(co > 0.0 && ci > 0.0)) {
        return vec4<f32>(0.0);
    }
    if (bsdf_is_lambert(b)) {
        let pdf = ci * BSDF_INV_PI;
        if (bsdf_lum(b.base) > 0.0) {
            return vec4<f32>(b.base * pdf, pdf);
        }
        return vec4<f32>(0.0);
    }
    let lobes = bsdf_lobes(b, co, eta);
    let h = normalize(wo + wi);
    let vh = max(dot(wo, h), 0.0);
    let fd = f_dielectric(b, vh, eta);
    let keep = 1.0 - b.mirror;
    var f = b.base * (keep * (1.0 - b.metallic) * (1.0 - b.transmission) * (1.0 - bsdf_max3(fd)) * BSDF_INV_PI * ci);
    var pdf = lobes.diff * ci * BSDF_INV_PI;
    if (!bsdf_is_delta(b)) {
        let a = bsdf_alpha(b);
        let d = ggx_d(h.z, a);
        let v = smith_v(co, ci, a);
        f += f_reflect(b, vh, eta) * (d * v * ci);
        pdf += lobes.spec * smith_g1(co, a) * d / (4.0 * co);
    }
    return vec4<f32>(f, pdf);
}

// A GGX visible normal for wo (Heitz 2018): bsdf.rs `sample_vndf`.
fn sample_vndf(wo: vec3<f32>, a: f32, u1: f32, u2: f32) -> vec3<f32> {
    let vh = normalize(vec3<f32>(a * wo.x, a * wo.y, wo.z));
    let lensq = vh.x * vh.x + vh.y * vh.y;
    var t1 = vec3<f32>(1.0, 0.0, 0.0);
    if (lensq > 0.0) {
        t1 = vec3<f32>(-vh.y, vh.x, 0.0) * (1.0 / sqrt(lensq));
    }
    let t2 = cross(vh, t1);
    let r = sqrt(u1);
    let phi = BSDF_TWO_PI * u2;
    let p1 = r * cos(phi);
    var p2 = r * sin(phi);
    let s = 0.5 * (1.0 + vh.z);
    p2 = (1.0 - s) * sqrt(max(1.0 - p1 * p1, 0.0)) + s * p2;
    let nh = t1 * p1 + t2 * p2 + vh * sqrt(max(1.0 - p1 * p1 - p2 * p2, 0.0));
    return normalize(vec3<f32>(a * nh.x, a * nh.y, max(nh.z, 0.0)));
}

fn cosine_hemisphere(u1: f32, u2: f32) -> vec3<f32> {
    let r = sqrt(u1);
    let phi = BSDF_TWO_PI * u2;
    return vec3<f32>(r * cos(phi), r * sin(phi), sqrt(max(1.0 - u1, 0.0)));
}

fn no_sample() -> BsdfSample {
    return BsdfSample(vec3<f32>(0.0), vec3<f32>(0.0), 0.0, false, false);
}

// bsdf.rs `sample_transmission`: refraction, always a delta for MIS.
fn sample_transmission(b: Bsdf, wo: vec3<f32>, eta: f32, u1: f32, u2: f32, p: f32) -> BsdfSample {
    let delta = bsdf_is_delta(b);
    var h = vec3<f32>(0.0, 0.0, 1.0);
    if (!delta) {
        h = sample_vndf(wo, bsdf_alpha(b), u1, u2);
    }
    let c = dot(wo, h);
    if (!(c > 0.0)) {
        return no_sample();
    }
    let inv_eta = 1.0 / eta;
    let sin2_t = inv_eta * inv_eta * (1.0 - c * c);
    if (sin2_t >= 1.0) {
        return no_sample();
    }
    let fd = bsdf_max3(f_dielectric(b, c, eta));
    let cos_t = sqrt(1.0 - sin2_t);
    let wi = normalize(-wo * inv_eta + h * (inv_eta * c - cos_t));
    var scale = (1.0 - b.mirror) * (1.0 - b.metallic) * b.transmission * (1.0 - fd) / p * inv_eta * inv_eta;
    if (!delta) {
        scale = scale * smith_g1(abs(wi.z), bsdf_alpha(b));
    }
    return BsdfSample(wi, b.base * scale, 0.0, true, true);
}

// bsdf.rs `sample`: u.x picks the lobe, u.y and u.z the direction.
fn bsdf_sample(b: Bsdf, wo: vec3<f32>, eta: f32, u: vec3<f32>) -> BsdfSample {
    let co = wo.z;
    if (!(co > 0.0)) {
        return no_sample();
    }
    if (bsdf_is_lambert(b)) {
        // f cos / pdf = base exactly.
        let wi = cosine_hemisphere(u.y, u.z);
        let pdf = wi.z * BSDF_INV_PI;
        if (!(pdf > 0.0 && bsdf_lum(b.base) > 0.0)) {
            return no_sample();
        }
        return BsdfSample(wi, b.base, pdf, false, true);
    }
    let lobes = bsdf_lobes(b, co, eta);
    let pick = u.x;
    if (pick < lobes.trans) {
        return sample_transmission(b, wo, eta, u.y, u.z, lobes.trans);
    }
    var wi: vec3<f32>;
    if (pick < lobes.trans + lobes.spec) {
        if (bsdf_is_delta(b)) {
            let weight = f_reflect(b, co, eta) * (1.0 / lobes.spec);
            return BsdfSample(vec3<f32>(-wo.x, -wo.y, wo.z), weight, 0.0, true, true);
        }
        let h = sample_vndf(wo, bsdf_alpha(b), u.y, u.z);
        wi = normalize(h * (2.0 * dot(wo, h)) - wo);
    } else {
        wi = cosine_hemisphere(u.y, u.z);
    }
    let e = bsdf_eval(b, wo, wi, eta);
    if (!(e.w > 0.0)) {
        return no_sample();
    }
    return BsdfSample(wi, e.xyz * (1.0 / e.w), e.w, false, true);
}

// bsdf.rs `Frame`: an orthonormal frame with n as z (Duff et al. 2017).
struct ShadingFrame {
    t1: vec3<f32>,
    t2: vec3<f32>,
    n: vec3<f32>,
}

fn shading_frame(n: vec3<f32>) -> ShadingFrame {
    let sign = select(1.0, -1.0, sign_bit(n.z));
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    return ShadingFrame(
        vec3<f32>(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        vec3<f32>(b, sign + n.y * n.y * a, -n.y),
        n,
    );
}

fn to_local(f: ShadingFrame, v: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(dot(v, f.t1), dot(v, f.t2), dot(v, f.n));
}

fn to_world(f: ShadingFrame, v: vec3<f32>) -> vec3<f32> {
    return f.t1 * v.x + f.t2 * v.y + f.n * v.z;
}
