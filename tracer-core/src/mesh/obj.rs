//! Wavefront OBJ with MTL materials, through `tobj`.

use std::borrow::Cow;
use std::cell::RefCell;
use std::path::Path;

use std::sync::Arc;

use super::{Mesh, MeshError, default_material};
use crate::assets::{AssetSource, dir_of, join};
use crate::material::{AlphaMode, Pbr};
use crate::scene::{MaterialDesc, Num, Vec3};
use crate::texture::{IDENTITY_UV, Image, TextureRef, Wrap};

pub(super) fn load(
    source: &dyn AssetSource,
    name: &str,
    bytes: &[u8],
    need_materials: bool,
) -> Result<Mesh, MeshError> {
    let path = Path::new(name);
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    // MTL libraries come through the same source, named beside the OBJ.
    let failed_libs = RefCell::new(Vec::<String>::new());
    let bytes = tobj_compatible(bytes);
    // On what tobj will read (decoded, polylines gone).
    check_face_indices(&bytes).map_err(|m| MeshError::new(path, format!("invalid OBJ: {m}")))?;
    let (models, materials) = tobj::load_obj_buf(
        &mut std::io::Cursor::new(&*bytes),
        &options,
        |lib: &Path| {
            let lib_name = join(dir_of(name), &lib.to_string_lossy());
            let result = source
                .read(&lib_name)
                .map_err(|_| tobj::LoadError::OpenFileFailed)
                .and_then(|data| {
                    let text = mtl_compatible(&data);
                    tobj::load_mtl_buf(&mut std::io::Cursor::new(text.as_bytes()))
                });
            if result.is_err() {
                failed_libs.borrow_mut().push(lib_name);
            }
            result
        },
    )
    .map_err(|e| {
        let message = match locate_parse_error(&bytes, &e) {
            Some((line, problem)) => format!("invalid OBJ: line {line}: {e}: {problem}"),
            None => format!("invalid OBJ: {e}"),
        };
        MeshError::new(path, message)
    })?;
    // A missing or unreadable library is common in downloaded models:
    // the default material stands in, and the user is told.
    let mut warnings = Vec::new();
    let materials = match materials {
        Ok(m) => m,
        Err(_) if !need_materials => Vec::new(),
        Err(e) => {
            let libs = failed_libs.into_inner().join(", ");
            warnings.push(format!(
                "cannot load its material library (mtllib {libs}): {e}; its faces use the default grey material \
                 (give the object a `material` to choose one)"
            ));
            Vec::new()
        }
    };
    for m in &materials {
        if m.optical_density.is_some_and(|n| n.is_nan() || n <= 0.0) {
            warnings.push(format!(
                "material {:?}: Ni {} is no index of refraction; 1 is used",
                m.name,
                m.optical_density.unwrap_or_default()
            ));
        }
    }
    let mut images = MtlImages {
        source,
        name,
        decoded: std::collections::HashMap::new(),
        warnings: Vec::new(),
    };
    let pbr: Vec<Option<Arc<Pbr>>> = materials
        .iter()
        .map(|m| mtl_maps(m, &mut images).map(Arc::new))
        .collect();
    warnings.append(&mut images.warnings);
    let any_uv = pbr.iter().flatten().any(|p| p.varies());
    let mut mesh = Mesh {
        warnings,
        materials: materials
            .iter()
            .map(|m| (m.name.clone(), map_material(m)))
            .collect(),
        pbr,
        ..Default::default()
    };
    let default_index = mesh.materials.len() as u32;
    let mut need_default = false;
    let any_normals = models.iter().any(|m| !m.mesh.normals.is_empty());
    for model in &models {
        let m = &model.mesh;
        let base = mesh.positions.len() as u32;
        let count = m.positions.len() / 3;
        mesh.positions
            .extend(m.positions.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
        if any_normals {
            if m.normals.len() == m.positions.len() {
                mesh.normals
                    .extend(m.normals.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
            } else {
                mesh.normals.extend(std::iter::repeat_n([0.0; 3], count));
            }
        }
        if any_uv {
            // OBJ's v runs up, texture space's down.
            if m.texcoords.len() / 2 == count {
                mesh.uvs[0].extend(m.texcoords.chunks_exact(2).map(|c| [c[0], 1.0 - c[1]]));
            } else {
                mesh.uvs[0].extend(std::iter::repeat_n([0.0; 2], count));
            }
        }
        let material = match m.material_id {
            Some(id) if id < materials.len() => id as u32,
            _ => {
                need_default = true;
                default_index
            }
        };
        for t in m.indices.chunks_exact(3) {
            mesh.triangles.push([base + t[0], base + t[1], base + t[2]]);
            mesh.triangle_materials.push(material);
        }
    }
    if need_default {
        mesh.materials.push(("default".into(), default_material()));
    }
    // `norm` maps need tangents: OBJ has none, so MikkTSpace's.
    let pbr = mesh.pbr.clone();
    super::tangents::complete(&mut mesh, &pbr);
    Ok(mesh)
}

/// A material name no MTL library defines: `usemtl` with no name (the
/// default material, for assimp and trimesh) is written as this one, which
/// tobj resolves to no material, since tobj refuses an empty name.
const NO_MATERIAL: &str = "\u{1}no material";

/// The OBJ as tobj can read it, each line kept where it was (so line
/// numbers stay those of the file), where it differs from what other
/// readers accept by choice rather than by a defect of the file:
/// - text in UTF-16 (with its byte-order mark) or with a UTF-8 one is
///   decoded; bytes that are not UTF-8 (Latin-1 names) become U+FFFD, as in
///   the MTL library, so names still match;
/// - `l` (polyline) records are blanked: tobj reads `l` as `f`, and a
///   polyline of three or more vertices would render as a filled polygon
///   (lines have no surface; `p` records tobj ignores itself);
/// - a statement continued with `\` at the end of its lines is joined;
/// - `usemtl` without a name selects the default material;
/// - when only some vertices have colours (`v x y z r g b`), the colours
///   are dropped (they are not rendered; tobj refuses the mix).
///
/// A file that needs none of this is passed on as it is.
fn tobj_compatible(bytes: &[u8]) -> Cow<'_, [u8]> {
    let utf16 = |rest: &[u8], be: bool| -> Cow<'static, str> {
        let units = rest.chunks_exact(2).map(|c| {
            let pair = [c[0], c[1]];
            if be {
                u16::from_be_bytes(pair)
            } else {
                u16::from_le_bytes(pair)
            }
        });
        Cow::Owned(
            char::decode_utf16(units)
                .map(|c| c.unwrap_or(char::REPLACEMENT_CHARACTER))
                .collect(),
        )
    };
    let text = if let Some(rest) = bytes.strip_prefix(b"\xFE\xFF") {
        utf16(rest, true)
    } else if let Some(rest) = bytes.strip_prefix(b"\xFF\xFE") {
        utf16(rest, false)
    } else {
        String::from_utf8_lossy(bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes))
    };
    fn keyword(line: &str) -> &str {
        line.split_whitespace().next().unwrap_or("")
    }
    let continued = |line: &str| line.trim_end().ends_with('\\');
    let (mut polylines, mut unnamed, mut coloured, mut plain) = (false, false, false, false);
    let mut joins = false;
    for line in text.split('\n') {
        joins |= continued(line);
        match keyword(line) {
            "l" => polylines = true,
            "usemtl" => unnamed |= line.split_whitespace().nth(1).is_none(),
            "v" => match line.split_whitespace().count() {
                7 => coloured = true,
                _ => plain = true,
            },
            _ => {}
        }
    }
    let drop_colours = coloured && plain;
    if !(polylines || unnamed || drop_colours || joins) {
        return match text {
            Cow::Borrowed(t) => Cow::Borrowed(t.as_bytes()),
            Cow::Owned(t) => Cow::Owned(t.into_bytes()),
        };
    }
    let mut out = String::with_capacity(text.len());
    let mut lines = text.split('\n');
    let mut joined;
    let mut first = true;
    while let Some(mut line) = lines.next() {
        if !first {
            out.push('\n');
        }
        first = false;
        // A statement continued over lines (`\` at the end) is read on its
        // first line; the lines it took stay, empty.
        let mut taken = 0;
        if continued(line) {
            let strip = |l: &str| {
                let t = l.trim_end();
                t.strip_suffix('\\').unwrap_or(t).to_string()
            };
            joined = strip(line);
            let mut more = true;
            while more && let Some(next) = lines.next() {
                taken += 1;
                more = continued(next);
                joined.push(' ');
                joined.push_str(&if more { strip(next) } else { next.to_string() });
            }
            line = &joined;
        }
        match keyword(line) {
            "l" => {}
            "usemtl" if line.split_whitespace().nth(1).is_none() => {
                out.push_str("usemtl ");
                out.push_str(NO_MATERIAL);
            }
            "v" if drop_colours && line.split_whitespace().count() == 7 => {
                let xyz: Vec<&str> = line.split_whitespace().take(4).collect();
                out.push_str(&xyz.join(" "));
            }
            _ => out.push_str(line),
        }
        for _ in 0..taken {
            out.push('\n');
        }
    }
    Cow::Owned(out.into_bytes())
}

/// Refuses faces whose texture-coordinate or normal index lies outside the
/// file's. tobj 4.0.5 resolves a relative index past the start (`-7` with
/// 3 defined) or a huge one to an index near `usize::MAX` and then computes
/// `vt * 2 + 1` or `vn * 3 + 2` unchecked: an overflow (a panic in checked
/// builds). Indices are resolved as tobj does: relative to the elements
/// defined before the line, absolute against all of the file's, 0 (or a
/// relative one just past the start) as none, and none checked for a kind
/// the file has none of. Lines tobj cannot read (not UTF-8) end the check:
/// tobj stops there with an error.
fn check_face_indices(bytes: &[u8]) -> Result<(), String> {
    let lines = || {
        bytes
            .split(|&b| b == b'\n')
            .map_while(|l| std::str::from_utf8(l).ok())
    };
    let kind = |word: Option<&str>| match word {
        Some("v") => Some(0),
        Some("vt") => Some(1),
        Some("vn") => Some(2),
        _ => None,
    };
    let mut total = [0i128; 3];
    for line in lines() {
        if let Some(k) = kind(line.split_whitespace().next()) {
            total[k] += 1;
        }
    }
    let mut before = [0i128; 3];
    for (n, line) in lines().enumerate() {
        let mut words = line.split_whitespace();
        let first = words.next();
        if let Some(k) = kind(first) {
            before[k] += 1;
        }
        if first != Some("f") {
            continue;
        }
        // tobj makes an empty polygon of it, and panics triangulating it.
        if words.clone().next().is_none() {
            return Err(format!("line {}: face without vertices", n + 1));
        }
        for word in words {
            for (k, part) in word.split('/').enumerate().skip(1).take(2) {
                // What tobj cannot parse it refuses itself.
                let Ok(x) = part.parse::<isize>() else {
                    continue;
                };
                let i = if x < 0 {
                    before[k] + x as i128
                } else {
                    x as i128 - 1
                };
                if i == -1 || total[k] == 0 || (0..total[k]).contains(&i) {
                    continue;
                }
                let what = ["vertex", "texture coordinate", "normal"][k];
                let (count, place) = if x < 0 {
                    (before[k], "before this line")
                } else {
                    (total[k], "in the file")
                };
                return Err(format!(
                    "line {}: face {what} index {x} is out of range ({count} defined {place})",
                    n + 1
                ));
            }
        }
    }
    Ok(())
}

/// Where tobj's parse error `e` is: tobj names no line, so the lines are
/// read again with tobj's rules for the record kind the error is about,
/// and the first that breaks them is named, with the word it cannot read
/// (line 12, `"3.1+e2" is not a number`). `None` for errors that are not
/// about one line.
fn locate_parse_error(bytes: &[u8], e: &tobj::LoadError) -> Option<(usize, String)> {
    use tobj::LoadError as E;
    let number = |w: &str| w.parse::<f32>().is_ok();
    // The first word of `words` that is not a number, or the count missing.
    let numbers = |words: &[&str], n: usize| -> Option<String> {
        match words.iter().take(n).find(|w| !number(w)) {
            Some(w) => Some(format!("{w:?} is not a number")),
            None if words.len() < n => Some(format!("{n} numbers expected, found {}", words.len())),
            None => None,
        }
    };
    let index = |w: &str| {
        w.split('/').count() <= 3
            && w.split('/')
                .all(|p| p.is_empty() || p.parse::<isize>().is_ok())
    };
    for (n, line) in bytes.split(|&b| b == b'\n').enumerate() {
        let line = String::from_utf8_lossy(line);
        let words: Vec<&str> = line.split_whitespace().collect();
        let Some((&key, rest)) = words.split_first() else {
            continue;
        };
        let problem = match (e, key) {
            (E::PositionParseError, "v") => numbers(rest, 3).or_else(|| match rest.len() {
                4 if !number(rest[3]) => Some(format!("{:?} is not a number", rest[3])),
                _ => None,
            }),
            (E::ColorParseError, "v") => matches!(rest.len(), 5 | 8..).then(|| {
                format!(
                    "{} values (3 numbers, then 1 weight or 3 colour components)",
                    rest.len()
                )
            }),
            (E::ScalingByZeroError, "v") => (rest.len() == 4 && rest[3].parse::<f32>() == Ok(0.0))
                .then(|| "weight w = 0".to_string()),
            (E::TexcoordParseError, "vt") => numbers(rest, 2),
            (E::NormalParseError, "vn") => numbers(rest, 3),
            (E::FaceParseError, "f") => rest
                .iter()
                .find(|w| !index(w))
                .map(|w| format!("{w:?} is not a vertex reference (v, v/vt, v//vn or v/vt/vn)")),
            _ => None,
        };
        if let Some(p) = problem {
            return Some((n + 1, p));
        }
    }
    None
}

/// An MTL library as tobj can read it: colour statements with one value
/// (`Kd 0.5`, which the format allows and means grey) are written with
/// three, since tobj indexes three and panics on fewer.
fn mtl_compatible(data: &[u8]) -> String {
    let text = String::from_utf8_lossy(data);
    let mut out = String::with_capacity(text.len() + 64);
    for line in text.lines() {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [k @ ("Ka" | "Kd" | "Ks" | "Ke" | "Tf"), v] if v.parse::<f32>().is_ok() => {
                out.push_str(&format!("{k} {v} {v} {v}"));
            }
            [k @ ("Ka" | "Kd" | "Ks" | "Ke" | "Tf"), ..] if words.len() < 4 => {
                // Nothing a colour can be made of: left out (defaults apply).
                out.push_str(&format!("# {k} ignored"));
            }
            _ => out.push_str(line),
        }
        out.push('\n');
    }
    out
}

/// MTL -> Blinn-Phong: Ka ambient (Kd when absent), Kd diffuse, Ks specular,
/// Ns shininess, d (or 1 - Tr) opacity, Ni ior; illum 3, 5 and 7 (the
/// "reflection on" models) make Ks's largest component the mirror weight.
fn map_material(m: &tobj::Material) -> MaterialDesc {
    let v = |c: Option<[f32; 3]>, d: [f64; 3]| Vec3(c.map(|c| c.map(f64::from)).unwrap_or(d));
    let diffuse = v(m.diffuse, [0.8; 3]);
    let specular = v(m.specular, [0.0; 3]);
    let opacity = match (
        m.dissolve,
        m.unknown_param
            .get("Tr")
            .and_then(|t| t.trim().parse::<f32>().ok()),
    ) {
        (Some(d), _) => d as f64,
        (None, Some(tr)) => 1.0 - tr as f64,
        (None, None) => 1.0,
    };
    let reflective = matches!(m.illumination_model, Some(3 | 5 | 7));
    MaterialDesc {
        ambient: v(m.ambient, diffuse.0),
        diffuse,
        specular,
        shininess: Num(m.shininess.map_or(1.0, f64::from)),
        reflectivity: Num(if reflective {
            specular.0.iter().cloned().fold(0.0, f64::max)
        } else {
            0.0
        }),
        transparency: Num((1.0 - opacity).clamp(0.0, 1.0)),
        ior: Num(m
            .optical_density
            .filter(|&n| n > 0.0)
            .map_or(1.0, f64::from)),
        gloss: Num(0.0),
        translucency: Num(0.0),
    }
}

/// An MTL material's maps and emission, or `None` when it has neither:
/// `map_Kd` (multiplying Kd and Ka), `Ke` and `map_Ke` (emission),
/// `map_d` (a cut-out where its value is below 0.5), each with the `-s`
/// and `-o` options (scale and offset of the texture coordinates) and
/// `-clamp on`; `norm` (a tangent-space normal map, as glTF's) or else
/// `bump`/`map_Bump` (a height field, scaled by its `-bm`).
fn mtl_maps(m: &tobj::Material, images: &mut MtlImages) -> Option<Pbr> {
    let what = |slot: &str| format!("material {:?} {slot}", m.name);
    let param = |k: &str| m.unknown_param.get(k).map(String::as_str);
    let mut tex = |spec: Option<&str>, srgb: bool, slot: &str| {
        spec.and_then(|s| images.texture(s, srgb, &what(slot)))
    };
    let base = tex(m.diffuse_texture.as_deref(), true, "map_Kd");
    let emissive_texture = tex(param("map_Ke"), true, "map_Ke");
    let alpha = tex(m.dissolve_texture.as_deref(), false, "map_d");
    let normal_texture = tex(param("norm"), false, "norm");
    let (bump_texture, bump_scale) = match (&normal_texture, m.normal_texture.as_deref()) {
        (None, Some(spec)) => (
            tex(Some(spec), false, "bump"),
            map_options(spec).map_or(1.0, |o| o.bm),
        ),
        _ => (None, 1.0),
    };
    let emissive = m
        .emissive
        .map_or([0.0; 3], |e| e.map(|c| f64::from(c).max(0.0)));
    let emissive = if emissive_texture.is_some() && m.emissive.is_none() {
        [1.0; 3]
    } else {
        emissive
    };
    if base.is_none()
        && emissive_texture.is_none()
        && alpha.is_none()
        && normal_texture.is_none()
        && bump_texture.is_none()
        && emissive == [0.0; 3]
    {
        return None;
    }
    Some(Pbr {
        mtl: true,
        alpha_mode: if alpha.is_some() {
            AlphaMode::Mask
        } else {
            AlphaMode::Opaque
        },
        base_color_texture: base,
        alpha_texture: alpha,
        emissive,
        emissive_texture,
        normal_texture,
        bump_texture,
        bump_scale,
        // OBJ has no notion of sidedness: both faces render.
        double_sided: true,
        ..Pbr::default()
    })
}

/// An MTL's images, each decoded once, by file name.
struct MtlImages<'a> {
    source: &'a dyn AssetSource,
    name: &'a str,
    decoded: std::collections::HashMap<String, Option<Arc<Image>>>,
    warnings: Vec<String>,
}

impl MtlImages<'_> {
    /// The map statement's arguments `spec` (options, then the file) as a
    /// texture, or `None` with a warning naming the file.
    fn texture(&mut self, spec: &str, srgb: bool, slot: &str) -> Option<TextureRef> {
        let MapOptions {
            file,
            transform,
            clamp,
            ..
        } = match map_options(spec) {
            Ok(o) => o,
            Err(e) => {
                self.warnings
                    .push(format!("{slot} {spec:?}: {e}; rendered without it"));
                return None;
            }
        };
        let path = join(dir_of(self.name), &file.replace('\\', "/"));
        let image = match self.decoded.get(&path) {
            Some(i) => i.clone(),
            None => {
                let got = self
                    .source
                    .read(&path)
                    .map_err(|e| format!("cannot be read ({e})"))
                    .and_then(|b| Image::decode(&path, &b));
                let got = match got {
                    Ok(i) => Some(Arc::new(i)),
                    Err(why) => {
                        self.warnings.push(format!(
                            "texture {path} {why}: {slot} and other uses of it render without it"
                        ));
                        None
                    }
                };
                self.decoded.insert(path, got.clone());
                got
            }
        }?;
        let wrap = if clamp {
            Wrap::ClampToEdge
        } else {
            Wrap::Repeat
        };
        Some(TextureRef {
            image,
            wrap: [wrap; 2],
            nearest: false,
            srgb,
            uv_set: 0,
            transform,
        })
    }
}

/// A map statement's file name, its `-o`/`-s` transform of the texture
/// coordinates and whether `-clamp on` is given. The transform acts on
/// OBJ's coordinates (v up): u' = s_u u + o_u, v' = s_v v + o_v, written
/// in texture space (v down, v = 1 - v_obj).
fn map_options(spec: &str) -> Result<MapOptions, String> {
    let words: Vec<&str> = spec.split_whitespace().collect();
    let (mut s, mut o, mut clamp, mut bm) = ([1.0f32; 3], [0.0f32; 3], false, 1.0f64);
    let mut i = 0;
    // Options and how many values each takes (at most).
    let takes = |opt: &str| match opt {
        "-s" | "-o" | "-t" => 3,
        "-mm" => 2,
        "-bm" | "-boost" | "-texres" | "-blendu" | "-blendv" | "-cc" | "-clamp" | "-imfchan"
        | "-type" => 1,
        _ => 0,
    };
    while i < words.len() && words[i].starts_with('-') && takes(words[i]) > 0 {
        let opt = words[i];
        let mut vals = Vec::new();
        i += 1;
        while vals.len() < takes(opt) && i + 1 < words.len() {
            match words[i].parse::<f32>() {
                Ok(v) if v.is_finite() => {
                    vals.push(v);
                    i += 1;
                }
                _ => break,
            }
            if !matches!(opt, "-s" | "-o" | "-t" | "-mm") {
                break;
            }
        }
        match opt {
            "-s" | "-o" => {
                if vals.is_empty() {
                    return Err(format!("{opt} needs numbers"));
                }
                let dst = if opt == "-s" { &mut s } else { &mut o };
                for (k, v) in vals.iter().enumerate() {
                    dst[k] = *v;
                }
                if opt == "-s" && vals.len() == 1 {
                    s[1] = vals[0];
                }
            }
            "-clamp" => {
                clamp = words.get(i).is_some_and(|w| *w == "on");
                i += 1;
            }
            "-bm" => {
                if let Some(&v) = vals.first() {
                    bm = v as f64;
                }
            }
            "-imfchan" | "-type" => i += 1,
            _ => {}
        }
    }
    let file = words[i.min(words.len())..].join(" ");
    if file.is_empty() {
        return Err("names no file".into());
    }
    // In texture space (v_t = 1 - v): u' = s_u u + o_u;
    // v_t' = 1 - (s_v (1 - v_t) + o_v) = s_v v_t + (1 - s_v - o_v).
    let transform = if s == [1.0; 3] && o == [0.0; 3] {
        IDENTITY_UV
    } else {
        [[s[0], 0.0, o[0]], [0.0, s[1], 1.0 - s[1] - o[1]]]
    };
    Ok(MapOptions {
        file,
        transform,
        clamp,
        bm,
    })
}

/// What a map statement says: its file, the `-o`/`-s` transform of the
/// texture coordinates (see [`map_options`]), `-clamp on`, and `-bm` (a
/// bump map's multiplier, 1 by default).
struct MapOptions {
    file: String,
    transform: [[f32; 3]; 2],
    clamp: bool,
    bm: f64,
}
