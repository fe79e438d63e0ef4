//! glTF 2.0 (.gltf with embedded or external buffers, .glb), through `gltf`.
//! Buffers are resolved here (data: URIs and files next to the model) so
//! the crate's image-decoding `import` feature is not needed: textures are
//! not used. Besides the triangles, the default scene's cameras and
//! `KHR_lights_punctual` lights are read (for model files as scenes).

use std::path::Path;

use base64::Engine;
use glam::{DMat3, DMat4, DVec3};
use gltf::mesh::Mode;

use std::sync::Arc;

use super::{
    Mesh, MeshError, ModelCamera, ModelLight, ModelLightKind, Projection, default_material,
};
use crate::assets::{AssetSource, dir_of, join};
use crate::material::{AlphaMode, Pbr};
use crate::texture::{IDENTITY_UV, Image, TextureRef, Wrap, uv_transform};

/// Mesh compression extensions, refused by name when a file requires them
/// (a file that only uses them carries uncompressed data as well).
const COMPRESSION: [(&str, &str); 2] = [
    ("KHR_draco_mesh_compression", "Draco mesh compression"),
    ("EXT_meshopt_compression", "meshoptimizer compression"),
];

/// Required extensions that Tessera reads: quantized attributes are
/// dequantized, lights become scene lights (docs/scene-format.md).
const READ: [&str; 3] = [
    "KHR_mesh_quantization",
    "KHR_lights_punctual",
    "EXT_mesh_gpu_instancing",
];

/// Extensions (by prefix) that change how a surface looks, never where it
/// is: a file that requires them renders, with a warning, without them.
const APPEARANCE: [&str; 7] = [
    "KHR_materials_",
    "KHR_texture_",
    "EXT_texture_",
    "KHR_technique_webgl",
    "KHR_lights_",
    "EXT_lights_",
    "KHR_xmp",
];

/// The crate's validation less what Tessera has no use for or has checked
/// itself (required extensions, above): a POSITION
/// accessor's `min` and `max` (bounds are taken from the vertices), which
/// the specification requires but writers leave out or get wrong.
fn validate(doc: &gltf::Document) -> Result<(), gltf::Error> {
    use gltf::json::validation::Validate;
    let root = doc.as_json();
    let mut errors = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |path, error| {
        let path = path();
        let p = path.as_str();
        let bounds = [".min", ".max"].map(|b| format!(".attributes[\"POSITION\"]{b}"));
        if !(bounds.iter().any(|b| p.ends_with(b.as_str()))
            || p.starts_with("extensionsRequired[")
                && error == gltf::json::validation::Error::Unsupported)
        {
            errors.push((path, error));
        }
    });
    if errors.is_empty() {
        Ok(())
    } else {
        Err(gltf::Error::Validation(errors))
    }
}

/// Deeper node hierarchies are rejected (they are surely cyclic or hostile).
const MAX_NODE_DEPTH: usize = 64;

pub(super) fn load(source: &dyn AssetSource, name: &str, bytes: &[u8]) -> Result<Mesh, MeshError> {
    let path = Path::new(name);
    let err = |m: String| MeshError::new(path, m);
    let invalid = |e: gltf::Error| err(format!("invalid glTF: {e}"));
    // gltf 1.4.1 subtracts the GLB header's 12 bytes from the length it
    // declares without a check (an overflow).
    if let Some(length) = bytes
        .strip_prefix(b"glTF")
        .and_then(|h| h.get(4..8))
        .map(|l| u32::from_le_bytes([l[0], l[1], l[2], l[3]]))
        && length < 12
    {
        return Err(err(format!(
            "invalid glTF: the GLB header declares a length of {length} bytes, less than its own 12"
        )));
    }
    // glTF 1.0 is a different format (objects where 2.0 has arrays): the
    // crate's error would be about a JSON type or a GLB version, so it is
    // named here.
    let gltf1 = |version: String| {
        err(format!(
            "is glTF 1.0 ({version}), which Tessera does not read: it reads glTF 2.0; \
             convert the file (for example with gltf-pipeline, or by importing it into \
             Blender and exporting glTF 2.0)"
        ))
    };
    // Parsed unchecked, then checked here for what the crate's own
    // validation indexes without a bounds check, then validated by
    // `validate` below rather than by `from_slice`: what Tessera does not
    // read (POSITION's min/max) is no reason to refuse a file.
    let gltf = gltf::Gltf::from_slice_without_validation(bytes)
        .map_err(|e| gltf1_version(bytes).map_or_else(|| invalid(e), gltf1))?;
    let version = &gltf.document.as_json().asset.version;
    if version.starts_with('1') {
        return Err(gltf1(format!("asset.version \"{version}\"")));
    }
    check_before_validation(gltf.document.as_json())
        .map_err(|m| err(format!("invalid glTF: {m}")))?;
    let doc = &gltf.document;
    let mut warnings = Vec::new();
    for ext in doc.extensions_required() {
        if let Some((_, what)) = COMPRESSION.iter().find(|(c, _)| *c == ext) {
            return Err(err(format!(
                "requires the extension {ext} ({what}), which Tessera does not decode: \
                 export the model without it"
            )));
        }
        if READ.contains(&ext) {
            continue;
        }
        if APPEARANCE.iter().any(|a| ext.starts_with(a)) {
            warnings.push(format!(
                "requires the extension {ext}, which Tessera does not read \
                 (it changes materials, textures or lights, not geometry): rendered without it"
            ));
        } else if !gltf::json::extensions::ENABLED_EXTENSIONS.contains(&ext) {
            return Err(err(format!(
                "requires the extension {ext}, which Tessera does not read"
            )));
        }
    }
    validate(doc).map_err(|e| {
        // A file that uses compression without requiring it should carry
        // uncompressed data too; one that does not fails validation on its
        // accessors without data, which is said as what it is.
        match doc
            .extensions_used()
            .find_map(|u| COMPRESSION.iter().find(|(c, _)| *c == u))
        {
            Some((ext, what)) => {
                let e = e.to_string();
                let e = e.trim_start_matches("invalid glTF: ").trim_end_matches(';');
                err(format!(
                    "uses the extension {ext} ({what}), which Tessera does not decode, \
                     and has no uncompressed data in its place ({e}): export the model without it"
                ))
            }
            None => err(format!("invalid glTF: {e}")),
        }
    })?;

    let mut buffers = Vec::new();
    for b in doc.buffers() {
        let data = match b.source() {
            gltf::buffer::Source::Bin => gltf.blob.clone().ok_or_else(|| {
                err(format!(
                    "invalid glTF: buffer {} uses the missing GLB binary chunk",
                    b.index()
                ))
            })?,
            gltf::buffer::Source::Uri(uri) => {
                if let Some(rest) = uri.strip_prefix("data:") {
                    let (_, b64) = rest.split_once(";base64,").ok_or_else(|| {
                        err(format!(
                            "invalid glTF: buffer {}: data URI is not base64",
                            b.index()
                        ))
                    })?;
                    base64::engine::general_purpose::STANDARD
                        .decode(b64)
                        .map_err(|e| {
                            err(format!(
                                "invalid glTF: buffer {}: bad base64: {e}",
                                b.index()
                            ))
                        })?
                } else {
                    // Through the scene's source, named beside the glTF file.
                    let file = join(dir_of(name), &percent_decode(uri));
                    source
                        .read(&file)
                        .map_err(|e| err(format!("cannot read buffer {}: {e}", b.index())))?
                        .to_vec()
                }
            }
        };
        if data.len() < b.length() {
            return Err(err(format!(
                "invalid glTF: buffer {} has {} bytes, the file declares {}",
                b.index(),
                data.len(),
                b.length()
            )));
        }
        buffers.push(data);
    }

    let mut images = Images {
        source,
        name,
        buffers: &buffers,
        decoded: vec![None; doc.images().len()],
        warnings: Vec::new(),
    };
    let pbr: Vec<Pbr> = doc
        .materials()
        .map(|m| read_material(&m, &mut images))
        .collect();
    warnings.append(&mut images.warnings);
    let mut mesh = Mesh {
        warnings,
        materials: doc
            .materials()
            .zip(&pbr)
            .map(|(m, p)| {
                (
                    m.name().unwrap_or("unnamed").to_string(),
                    p.whitted(p.base_color, p.metallic, p.roughness),
                )
            })
            .collect(),
        pbr: pbr.into_iter().map(|p| Some(Arc::new(p))).collect(),
        ..Default::default()
    };
    let default_index = mesh.materials.len() as u32;
    let mut need_default = false;

    // Instances: the default (or first) scene's node tree; without scenes, each mesh once.
    let mut placed = Placed {
        gpu_instances: gpu_instancing(bytes, doc, &buffers).map_err(&err)?,
        ..Default::default()
    };
    match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(scene) => {
            for node in scene.nodes() {
                collect(node, DMat4::IDENTITY, 0, &mut placed).map_err(&err)?;
            }
        }
        None => placed
            .meshes
            .extend(doc.meshes().map(|m| (m, DMat4::IDENTITY))),
    }
    mesh.cameras = placed.cameras;
    mesh.lights = placed.lights;
    let instances = placed.meshes;

    // A mesh placed by several nodes (or copies of EXT_mesh_gpu_instancing)
    // is read once, in its own space, as an instanced part that the world
    // traces through a two-level tree; a mesh placed once is transformed
    // into the model's triangles.
    let mut uses = std::collections::HashMap::<usize, usize>::new();
    for (gmesh, _) in &instances {
        *uses.entry(gmesh.index()).or_default() += 1;
    }
    let mut part_of = std::collections::HashMap::<usize, usize>::new();
    let mut parts: Vec<(Geometry, Vec<[f64; 16]>)> = Vec::new();
    let mut main = Geometry::default();
    for (gmesh, xf) in &instances {
        let (geo, xf) = if uses[&gmesh.index()] > 1 {
            match part_of.get(&gmesh.index()) {
                Some(&k) => {
                    let part: &mut (Geometry, Vec<[f64; 16]>) = &mut parts[k];
                    part.1.push(xf.to_cols_array());
                    continue;
                }
                None => {
                    part_of.insert(gmesh.index(), parts.len());
                    parts.push((Geometry::default(), vec![xf.to_cols_array()]));
                    let last = parts.len() - 1;
                    (&mut parts[last].0, &DMat4::IDENTITY)
                }
            }
        } else {
            (&mut main, xf)
        };
        let normal_xf = DMat3::from_mat4(*xf).inverse().transpose();
        let flip = xf.determinant() < 0.0;
        for prim in gmesh.primitives() {
            let at =
                |what: &str| format!("mesh {} primitive {}: {what}", gmesh.index(), prim.index());
            if !matches!(
                prim.mode(),
                Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
            ) {
                continue; // points and lines have no surface
            }
            // The crate trusts counts, strides and offsets (it panics or
            // allocates what a count asks): checked against the buffers first.
            let attrs = prim.attributes().filter_map(|(s, a)| match s {
                gltf::Semantic::Positions => Some(("POSITION", a)),
                gltf::Semantic::Normals => Some(("NORMAL", a)),
                gltf::Semantic::TexCoords(0) => Some(("TEXCOORD_0", a)),
                gltf::Semantic::TexCoords(1) => Some(("TEXCOORD_1", a)),
                gltf::Semantic::Colors(0) => Some(("COLOR_0", a)),
                _ => None,
            });
            for (what, acc) in attrs.chain(prim.indices().map(|a| ("indices", a))) {
                check_accessor_type(what, &acc).map_err(|m| err(at(&m)))?;
                check_accessor(&acc, &buffers).map_err(|m| err(at(&m)))?;
            }
            let reader = prim.reader(|b| buffers.get(b.index()).map(|d| d.as_slice()));
            let mut positions: Vec<[f32; 3]> = prim
                .get(&gltf::Semantic::Positions)
                .and_then(|a| read_vec3(&a, &buffers))
                .ok_or_else(|| err(at("positions are missing or lie outside their buffer")))?;
            let base = geo.mesh.positions.len() as u32;
            let n = positions.len() as u32;
            let nv = positions.len();
            for p in &mut positions {
                *p = xf
                    .transform_point3(DVec3::from_array(p.map(f64::from)))
                    .as_vec3()
                    .to_array();
            }
            append(&mut geo.mesh.positions, positions);
            let read_normals = match prim.get(&gltf::Semantic::Normals) {
                Some(a) => Some(
                    read_vec3(&a, &buffers)
                        .ok_or_else(|| err(at("normals lie outside their buffer")))?,
                ),
                None => None,
            };
            let normals = read_normals.map(|mut ns| {
                for v in &mut ns {
                    *v = (normal_xf * DVec3::from_array(v.map(f64::from)))
                        .as_vec3()
                        .to_array();
                }
                ns
            });
            per_vertex(&mut geo.normals, base as usize, nv, [0.0; 3], normals)
                .map_err(|_| err(at("normal count differs from position count")))?;
            for (k, uv) in geo.uvs.iter_mut().enumerate() {
                let read = reader
                    .read_tex_coords(k as u32)
                    .map(|t| t.into_f32().collect());
                per_vertex(uv, base as usize, nv, [0.0; 2], read).map_err(|_| {
                    err(at(&format!(
                        "TEXCOORD_{k} count differs from position count"
                    )))
                })?;
            }
            // TANGENT (VEC4 of float; a quantized one is left for MikkTSpace).
            let tangents = prim.get(&gltf::Semantic::Tangents).filter(|a| {
                a.dimensions() == gltf::accessor::Dimensions::Vec4
                    && a.data_type() == gltf::accessor::DataType::F32
                    && check_accessor(a, &buffers).is_ok()
            });
            let read = tangents.and_then(|_| reader.read_tangents()).map(|t| {
                let linear = DMat3::from_mat4(*xf);
                let sign = if flip { -1.0 } else { 1.0 };
                t.map(|[x, y, z, w]| {
                    let v = (linear * DVec3::new(x as f64, y as f64, z as f64))
                        .normalize_or_zero()
                        .as_vec3();
                    let w = if w < 0.0 { -sign } else { sign };
                    [v.x, v.y, v.z, w]
                })
                .collect()
            });
            per_vertex(&mut geo.tangents, base as usize, nv, [0.0; 4], read)
                .map_err(|_| err(at("TANGENT count differs from position count")))?;
            let read: Option<Vec<[f32; 4]>> =
                reader.read_colors(0).map(|c| c.into_rgba_f32().collect());
            if read.is_some()
                && let Some(Some(p)) = prim.material().index().and_then(|i| mesh.pbr.get_mut(i))
            {
                Arc::make_mut(p).vertex_colors = true;
            }
            per_vertex(&mut geo.colors, base as usize, nv, [1.0; 4], read)
                .map_err(|_| err(at("COLOR_0 count differs from position count")))?;
            let material = match prim.material().index() {
                Some(i) => i as u32,
                None => {
                    need_default = true;
                    default_index
                }
            };
            let out = &mut geo.mesh;
            if prim.mode() == Mode::Triangles {
                let count = prim.indices().map_or(n as usize, |a| a.count()) / 3;
                out.triangles.reserve(count);
                out.triangle_materials.reserve(count);
            }
            let mut push = |t: [u32; 3]| -> Result<(), MeshError> {
                if let Some(bad) = t.iter().find(|&&i| i >= n) {
                    return Err(err(at(&format!("index {bad} out of range ({n} vertices)"))));
                }
                let t = t.map(|i| base + i);
                out.triangles
                    .push(if flip { [t[0], t[2], t[1]] } else { t });
                out.triangle_materials.push(material);
                Ok(())
            };
            match (prim.mode(), reader.read_indices()) {
                // A list's triangles straight from the buffer (a big
                // mesh's load holds no copy of its indices).
                (Mode::Triangles, Some(i)) => {
                    let mut i = i.into_u32();
                    while let Some(a) = i.next() {
                        match (i.next(), i.next()) {
                            (Some(b), Some(c)) => push([a, b, c])?,
                            // Indices left over past the last whole
                            // triangle draw nothing, but are checked.
                            (b, _) => {
                                if let Some(bad) =
                                    [Some(a), b].into_iter().flatten().find(|&i| i >= n)
                                {
                                    return Err(err(at(&format!(
                                        "index {bad} out of range ({n} vertices)"
                                    ))));
                                }
                            }
                        }
                    }
                }
                (mode, read) => {
                    let indices: Vec<u32> = match read {
                        Some(i) => i.into_u32().collect(),
                        None => (0..n).collect(),
                    };
                    match mode {
                        Mode::Triangles => {
                            for t in indices.chunks_exact(3) {
                                push([t[0], t[1], t[2]])?;
                            }
                        }
                        // Strips alternate winding; fans share their first vertex.
                        Mode::TriangleStrip => {
                            for i in 2..indices.len() {
                                push(if i % 2 == 0 {
                                    [indices[i - 2], indices[i - 1], indices[i]]
                                } else {
                                    [indices[i - 1], indices[i - 2], indices[i]]
                                })?;
                            }
                        }
                        _ => {
                            for i in 2..indices.len() {
                                push([indices[0], indices[i - 1], indices[i]])?;
                            }
                        }
                    }
                }
            }
        }
    }
    main.finish_into(&mut mesh);
    let pbr = mesh.pbr.clone();
    super::tangents::complete(&mut mesh, &pbr);
    for (geo, transforms) in parts {
        let mut part = Mesh::default();
        geo.finish_into(&mut part);
        super::tangents::complete(&mut part, &pbr);
        mesh.instanced.push(super::InstancedPart {
            mesh: part,
            transforms,
        });
    }
    if need_default {
        mesh.materials.push(("default".into(), default_material()));
    }
    Ok(mesh)
}

/// What gltf-json's validation trusts: it looks up each primitive's
/// POSITION accessor by index (for its min and max) before reporting an
/// index out of range, and panics on one (gltf-json 1.4.1, mesh.rs).
fn check_before_validation(root: &gltf::json::Root) -> Result<(), String> {
    let accessors = root.accessors.len();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let position =
                gltf::json::validation::Checked::Valid(gltf::json::mesh::Semantic::Positions);
            if let Some(i) = prim.attributes.get(&position)
                && i.value() >= accessors
            {
                return Err(format!(
                    "meshes[{m}].primitives[{p}].attributes[\"POSITION\"]: accessor {} does not exist (the file has {accessors} accessors)",
                    i.value()
                ));
            }
        }
    }
    Ok(())
}

/// Geometry being read: the model's own, or an instanced part's. Its
/// optional per-vertex attributes stay empty while no primitive has them
/// ([`per_vertex`]).
#[derive(Default)]
struct Geometry {
    mesh: Mesh,
    normals: Vec<[f32; 3]>,
    /// Texture coordinates and colours of this target's vertices (each
    /// target, the placed-once triangles or an instanced part, has its own
    /// vertex list).
    uvs: [Vec<[f32; 2]>; 2],
    colors: Vec<[f32; 4]>,
    tangents: Vec<[f32; 4]>,
}

impl Geometry {
    /// Moves the geometry read into `out`.
    fn finish_into(self, out: &mut Mesh) {
        out.positions = self.mesh.positions;
        out.triangles = self.mesh.triangles;
        out.triangle_materials = self.mesh.triangle_materials;
        out.normals = self.normals;
        out.uvs = self.uvs;
        out.colors = self.colors;
        out.tangents = self.tangents;
    }
}

/// Appends `values` to `list`, taking them whole when `list` is empty (a
/// big mesh's one primitive is then never copied).
fn append<T: Copy>(list: &mut Vec<T>, values: Vec<T>) {
    if list.is_empty() {
        *list = values;
    } else {
        list.extend_from_slice(&values);
    }
}

/// Appends one primitive's values of an optional per-vertex attribute
/// (its `n` vertices follow `before` earlier ones): its own, or `default`
/// for each vertex where it has none but an earlier primitive had some.
/// A list no primitive has values for stays empty; the first primitive
/// that has some fills in `default` for the vertices before its own.
/// Err when it has other than `n` values.
fn per_vertex<T: Copy>(
    list: &mut Vec<T>,
    before: usize,
    n: usize,
    default: T,
    values: Option<Vec<T>>,
) -> Result<(), ()> {
    match values {
        Some(v) if v.len() != n => Err(()),
        Some(v) => {
            list.resize(before, default);
            append(list, v);
            Ok(())
        }
        None => {
            if !list.is_empty() {
                list.resize(before + n, default);
            }
            Ok(())
        }
    }
}

/// What the default scene's nodes place, in the order of a depth-first walk.
#[derive(Default)]
struct Placed<'a> {
    meshes: Vec<(gltf::Mesh<'a>, DMat4)>,
    /// `EXT_mesh_gpu_instancing`: a node's instance transforms, by node index.
    gpu_instances: std::collections::HashMap<usize, Vec<DMat4>>,
    cameras: Vec<ModelCamera>,
    lights: Vec<ModelLight>,
}

fn collect<'a>(
    node: gltf::Node<'a>,
    parent: DMat4,
    depth: usize,
    out: &mut Placed<'a>,
) -> Result<(), String> {
    if depth > MAX_NODE_DEPTH {
        return Err(format!(
            "invalid glTF: node hierarchy deeper than {MAX_NODE_DEPTH} (a cycle?) at node {}",
            node.index()
        ));
    }
    let m = node.transform().matrix();
    let xf = parent * DMat4::from_cols_array_2d(&m.map(|c| c.map(f64::from)));
    if let Some(mesh) = node.mesh() {
        match out.gpu_instances.get(&node.index()) {
            // Each instance is placed in the node's space.
            Some(list) => out
                .meshes
                .extend(list.iter().map(|t| (mesh.clone(), xf * *t))),
            None => out.meshes.push((mesh, xf)),
        }
    }
    // Cameras and lights look down their node's -Z axis, +Y up.
    let position = xf.transform_point3(DVec3::ZERO).to_array();
    let forward = xf.transform_vector3(DVec3::NEG_Z).normalize_or_zero();
    let bad = |what: &str| {
        format!(
            "invalid glTF: node {} places its {what} with a transform that is not invertible or not finite",
            node.index()
        )
    };
    if let Some(camera) = node.camera() {
        if forward == DVec3::ZERO || !forward.is_finite() || !position.iter().all(|c| c.is_finite())
        {
            return Err(bad("camera"));
        }
        let projection = match camera.projection() {
            gltf::camera::Projection::Perspective(p) => Projection::Perspective {
                yfov: p.yfov() as f64,
                aspect_ratio: p.aspect_ratio().map(f64::from),
            },
            gltf::camera::Projection::Orthographic(o) => Projection::Orthographic {
                xmag: o.xmag() as f64,
                ymag: o.ymag() as f64,
            },
        };
        out.cameras.push(ModelCamera {
            index: camera.index(),
            name: camera.name().or(node.name()).map(str::to_string),
            projection,
            position,
            forward: forward.to_array(),
            up: xf.transform_vector3(DVec3::Y).to_array(),
        });
    }
    if let Some(light) = node.light() {
        use gltf::khr_lights_punctual::Kind;
        if forward == DVec3::ZERO || !forward.is_finite() || !position.iter().all(|c| c.is_finite())
        {
            return Err(bad("light"));
        }
        let kind = match light.kind() {
            Kind::Point => ModelLightKind::Point,
            Kind::Directional => ModelLightKind::Directional,
            Kind::Spot {
                inner_cone_angle,
                outer_cone_angle,
            } => ModelLightKind::Spot {
                inner: inner_cone_angle as f64,
                outer: outer_cone_angle as f64,
            },
        };
        let color = light.color().map(f64::from);
        let intensity = light.intensity() as f64;
        let name = light.name().or(node.name()).map(str::to_string);
        if !(color.iter().all(|c| c.is_finite() && *c >= 0.0)
            && intensity.is_finite()
            && intensity >= 0.0)
        {
            return Err(format!(
                "invalid glTF: light {} ({:?}): color {color:?} and intensity {intensity} must be finite and >= 0",
                light.index(),
                name.as_deref().unwrap_or("unnamed")
            ));
        }
        out.lights.push(ModelLight {
            index: light.index(),
            name,
            kind,
            color,
            intensity,
            position,
            direction: forward.to_array(),
        });
    }
    for child in node.children() {
        collect(child, xf, depth + 1, out)?;
    }
    Ok(())
}

/// `EXT_mesh_gpu_instancing` of every node that has it: its instances'
/// transforms (translation, rotation, scale, each optional), by node index.
/// Read from the JSON itself: the `gltf` crate does not know the extension.
fn gpu_instancing(
    bytes: &[u8],
    doc: &gltf::Document,
    buffers: &[Vec<u8>],
) -> Result<std::collections::HashMap<usize, Vec<DMat4>>, String> {
    use std::collections::HashMap;
    const EXT: &str = "EXT_mesh_gpu_instancing";
    let mut out = HashMap::new();
    if !doc.extensions_used().any(|e| e == EXT) {
        return Ok(out);
    }
    #[derive(serde::Deserialize)]
    struct Ext {
        #[serde(default)]
        attributes: HashMap<String, usize>,
    }
    #[derive(serde::Deserialize, Default)]
    struct Exts {
        #[serde(rename = "EXT_mesh_gpu_instancing")]
        ext: Option<Ext>,
    }
    #[derive(serde::Deserialize)]
    struct Node {
        #[serde(default)]
        extensions: Option<Exts>,
    }
    #[derive(serde::Deserialize)]
    struct Root {
        #[serde(default)]
        nodes: Vec<Node>,
    }
    // A GLB's JSON is its first chunk, after the 12-byte header and the
    // chunk's 8-byte header.
    let json = match bytes.strip_prefix(b"glTF") {
        Some(_) => {
            let len = bytes
                .get(12..16)
                .map(|l| u32::from_le_bytes([l[0], l[1], l[2], l[3]]) as usize)
                .unwrap_or(0);
            bytes.get(20..20 + len).unwrap_or(&[])
        }
        None => bytes,
    };
    let root: Root = gltf::json::deserialize::from_slice(json)
        .map_err(|e| format!("invalid glTF: {EXT}: {e}"))?;
    for (n, node) in root.nodes.iter().enumerate() {
        let Some(ext) = node.extensions.as_ref().and_then(|e| e.ext.as_ref()) else {
            continue;
        };
        let at = |m: String| format!("node {n}: {EXT}: {m}");
        let mut count = None;
        let mut read = |name: &str, dims: usize| -> Result<Option<Vec<f32>>, String> {
            let Some(&i) = ext.attributes.get(name) else {
                return Ok(None);
            };
            let acc = doc
                .accessors()
                .nth(i)
                .ok_or_else(|| at(format!("{name} accessor {i} does not exist")))?;
            let ok_dims = match dims {
                3 => acc.dimensions() == gltf::accessor::Dimensions::Vec3,
                _ => acc.dimensions() == gltf::accessor::Dimensions::Vec4,
            };
            if !ok_dims || acc.data_type() != gltf::accessor::DataType::F32 {
                return Err(at(format!(
                    "{name} accessor {i} must hold VEC{dims} of float"
                )));
            }
            check_accessor(&acc, buffers).map_err(|m| at(format!("{name}: {m}")))?;
            if *count.get_or_insert(acc.count()) != acc.count() {
                return Err(at(format!(
                    "{name} has {} elements, another attribute {}",
                    acc.count(),
                    count.unwrap_or(0)
                )));
            }
            let get = |b: gltf::Buffer| buffers.get(b.index()).map(|d| d.as_slice());
            let values: Option<Vec<f32>> = if dims == 3 {
                gltf::accessor::Iter::<[f32; 3]>::new(acc.clone(), get)
                    .map(|it| it.flatten().collect())
            } else {
                gltf::accessor::Iter::<[f32; 4]>::new(acc.clone(), get)
                    .map(|it| it.flatten().collect())
            };
            let values = values.ok_or_else(|| at(format!("{name} lies outside its buffer")))?;
            if values.iter().any(|v| !v.is_finite()) {
                return Err(at(format!("{name} holds a value that is not finite")));
            }
            Ok(Some(values))
        };
        let t = read("TRANSLATION", 3)?;
        let r = read("ROTATION", 4)?;
        let s = read("SCALE", 3)?;
        let n_inst =
            count.ok_or_else(|| at("has none of TRANSLATION, ROTATION and SCALE".to_string()))?;
        let list = (0..n_inst)
            .map(|k| {
                let v3 = |a: &Option<Vec<f32>>, d: f64| {
                    a.as_ref().map_or(DVec3::splat(d), |a| {
                        DVec3::new(a[3 * k] as f64, a[3 * k + 1] as f64, a[3 * k + 2] as f64)
                    })
                };
                let q = r.as_ref().map_or(glam::DQuat::IDENTITY, |a| {
                    glam::DQuat::from_xyzw(
                        a[4 * k] as f64,
                        a[4 * k + 1] as f64,
                        a[4 * k + 2] as f64,
                        a[4 * k + 3] as f64,
                    )
                    .normalize()
                });
                DMat4::from_scale_rotation_translation(v3(&s, 1.0), q, v3(&t, 0.0))
            })
            .collect::<Vec<_>>();
        if let Some(k) = list.iter().position(|m| !m.is_finite()) {
            return Err(at(format!(
                "instance {k}'s transform is not finite (a zero ROTATION quaternion?)"
            )));
        }
        out.insert(n, list);
    }
    Ok(out)
}

/// The version of a glTF 1.0 file (binary glTF 1.0, or JSON whose
/// `asset.version` starts with "1"), `None` for anything else.
fn gltf1_version(bytes: &[u8]) -> Option<String> {
    if let Some(v) = bytes.strip_prefix(b"glTF").and_then(|h| h.get(..4)) {
        let v = u32::from_le_bytes([v[0], v[1], v[2], v[3]]);
        return (v == 1).then(|| "binary glTF, GLB version 1".to_string());
    }
    #[derive(serde::Deserialize)]
    struct Asset {
        version: Option<gltf::json::Value>,
    }
    #[derive(serde::Deserialize)]
    struct Head {
        asset: Option<Asset>,
    }
    let head: Head = gltf::json::deserialize::from_slice(bytes).ok()?;
    let version = head.asset?.version?;
    let text = match &version {
        gltf::json::Value::String(s) => s.clone(),
        gltf::json::Value::Number(n) => n.to_string(),
        _ => return None,
    };
    text.starts_with('1')
        .then(|| format!("asset.version {version}"))
}

/// A VEC3 accessor's elements as f32: floats as they are, integers
/// dequantized as `KHR_mesh_quantization` says (normalized: c / 127,
/// c / 255, c / 32767 or c / 65535, signed ones at least -1; otherwise
/// the integer's value). Sparse accessors included. `None` when the data
/// lies outside its buffers (checked before by [`check_accessor`]).
fn read_vec3(acc: &gltf::Accessor, buffers: &[Vec<u8>]) -> Option<Vec<[f32; 3]>> {
    use gltf::accessor::{DataType, Item, Iter};
    fn read<'s, T: Item + Copy>(
        acc: &gltf::Accessor<'s>,
        buffers: &'s [Vec<u8>],
        f: impl Fn(T) -> f32,
    ) -> Option<Vec<[f32; 3]>> {
        let get = |b: gltf::Buffer| buffers.get(b.index()).map(|d| d.as_slice());
        Some(
            Iter::<[T; 3]>::new(acc.clone(), get)?
                .map(|v| v.map(&f))
                .collect(),
        )
    }
    let norm = acc.normalized();
    match acc.data_type() {
        DataType::F32 => read::<f32>(acc, buffers, |c| c),
        DataType::I8 if norm => read::<i8>(acc, buffers, |c| (c as f32 / 127.0).max(-1.0)),
        DataType::U8 if norm => read::<u8>(acc, buffers, |c| c as f32 / 255.0),
        DataType::I16 if norm => read::<i16>(acc, buffers, |c| (c as f32 / 32767.0).max(-1.0)),
        DataType::U16 if norm => read::<u16>(acc, buffers, |c| c as f32 / 65535.0),
        DataType::I8 => read::<i8>(acc, buffers, f32::from),
        DataType::U8 => read::<u8>(acc, buffers, f32::from),
        DataType::I16 => read::<i16>(acc, buffers, f32::from),
        DataType::U16 => read::<u16>(acc, buffers, f32::from),
        DataType::U32 => None,
    }
}

/// A glTF material as authored (`Pbr`): factors, extensions and the
/// textures, each decoded once (a texture that cannot be read is a
/// warning naming its file; the material renders without it). Its
/// Whitted mapping is `Pbr::whitted` (docs/meshes.md).
fn read_material(m: &gltf::Material, images: &mut Images) -> Pbr {
    let pbr = m.pbr_metallic_roughness();
    let what = |slot: &str| {
        format!(
            "material {} ({:?}) {slot}",
            m.index().map_or("default".to_string(), |i| i.to_string()),
            m.name().unwrap_or("unnamed")
        )
    };
    let info = |i: Option<gltf::texture::Info>, srgb: bool, slot: &str, images: &mut Images| {
        let i = i?;
        let (transform, set) = match i.texture_transform() {
            Some(t) => (
                uv_transform(t.offset(), t.rotation(), t.scale()),
                t.tex_coord().unwrap_or(i.tex_coord()),
            ),
            None => (IDENTITY_UV, i.tex_coord()),
        };
        images.texture(&i.texture(), srgb, set, transform, &what(slot))
    };
    let specular = m.specular();
    Pbr {
        base_color: pbr.base_color_factor().map(f64::from),
        base_color_texture: info(pbr.base_color_texture(), true, "baseColorTexture", images),
        metallic: pbr.metallic_factor() as f64,
        roughness: pbr.roughness_factor() as f64,
        metallic_roughness_texture: info(
            pbr.metallic_roughness_texture(),
            false,
            "metallicRoughnessTexture",
            images,
        ),
        emissive: m
            .emissive_factor()
            .map(|e| e as f64 * m.emissive_strength().unwrap_or(1.0) as f64),
        emissive_texture: info(m.emissive_texture(), true, "emissiveTexture", images),
        normal_texture: m.normal_texture().and_then(|n| {
            images.texture(
                &n.texture(),
                false,
                n.tex_coord(),
                IDENTITY_UV,
                &what("normalTexture"),
            )
        }),
        normal_scale: m.normal_texture().map_or(1.0, |n| n.scale() as f64),
        occlusion_texture: m.occlusion_texture().and_then(|o| {
            images.texture(
                &o.texture(),
                false,
                o.tex_coord(),
                IDENTITY_UV,
                &what("occlusionTexture"),
            )
        }),
        occlusion_strength: m.occlusion_texture().map_or(1.0, |o| o.strength() as f64),
        alpha_mode: match m.alpha_mode() {
            gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
            gltf::material::AlphaMode::Mask => AlphaMode::Mask,
            gltf::material::AlphaMode::Blend => AlphaMode::Blend,
        },
        alpha_cutoff: m.alpha_cutoff().unwrap_or(0.5) as f64,
        double_sided: m.double_sided(),
        ior: m.ior().map_or(1.5, f64::from),
        transmission: m
            .transmission()
            .map_or(0.0, |t| t.transmission_factor() as f64),
        attenuation_color: m
            .volume()
            .map_or([1.0; 3], |v| v.attenuation_color().map(f64::from)),
        attenuation_distance: m
            .volume()
            .map_or(f64::INFINITY, |v| v.attenuation_distance() as f64),
        specular_factor: specular
            .as_ref()
            .map_or(1.0, |s| s.specular_factor() as f64),
        specular_color: specular
            .as_ref()
            .map_or([1.0; 3], |s| s.specular_color_factor().map(f64::from)),
        ..Pbr::default()
    }
}

/// A glTF file's images, decoded when a material first uses them.
struct Images<'a> {
    source: &'a dyn AssetSource,
    name: &'a str,
    buffers: &'a [Vec<u8>],
    /// Per image: not tried yet, or what decoding gave.
    decoded: Vec<Option<Option<Arc<Image>>>>,
    warnings: Vec<String>,
}

impl Images<'_> {
    /// The texture `t` as a material's `slot` uses it, or `None` (with a
    /// warning) when its image cannot be read.
    fn texture(
        &mut self,
        t: &gltf::Texture,
        srgb: bool,
        uv_set: u32,
        transform: [[f32; 3]; 2],
        slot: &str,
    ) -> Option<TextureRef> {
        // A texture without a source (`allow_empty_texture`) has nothing to sample.
        let img = t.source()?;
        let i = img.index();
        if self.decoded[i].is_none() {
            let (file, got) = self.decode(&img);
            let got = got.map(Arc::new).map_err(|why| {
                self.warnings.push(format!(
                    "texture {file} {why}: {slot} and other uses of it render without it (its factor alone)"
                ))
            });
            self.decoded[i] = Some(got.ok());
        }
        let image = self.decoded[i].clone().flatten()?;
        if uv_set > 1 {
            self.warnings.push(format!(
                "{slot} uses TEXCOORD_{uv_set}; Tessera reads TEXCOORD_0 and _1: rendered without it"
            ));
            return None;
        }
        let sampler = t.sampler();
        let wrap = |w: gltf::texture::WrappingMode| match w {
            gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
            gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
            gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
        };
        Some(TextureRef {
            image,
            wrap: [wrap(sampler.wrap_s()), wrap(sampler.wrap_t())],
            nearest: sampler.mag_filter() == Some(gltf::texture::MagFilter::Nearest),
            srgb,
            uv_set,
            transform,
        })
    }

    /// The image's file (for messages) and its decoded texels.
    fn decode(&self, img: &gltf::Image) -> (String, Result<Image, String>) {
        match img.source() {
            gltf::image::Source::Uri { uri, .. } => {
                if let Some(rest) = uri.strip_prefix("data:") {
                    let file = format!("image {} (a data URI)", img.index());
                    let bytes = rest
                        .split_once(";base64,")
                        .ok_or_else(|| "is a data URI that is not base64".to_string())
                        .and_then(|(_, b64)| {
                            base64::engine::general_purpose::STANDARD
                                .decode(b64)
                                .map_err(|e| format!("has bad base64: {e}"))
                        });
                    let got = bytes.and_then(|b| Image::decode(&file, &b));
                    return (file, got);
                }
                let file = join(dir_of(self.name), &percent_decode(uri));
                let got = self
                    .source
                    .read(&file)
                    .map_err(|e| format!("cannot be read ({e})"))
                    .and_then(|b| Image::decode(&file, &b));
                (file, got)
            }
            gltf::image::Source::View { view, .. } => {
                let file = format!("image {} (buffer view {})", img.index(), view.index());
                let bytes = self
                    .buffers
                    .get(view.buffer().index())
                    .and_then(|b| b.get(view.offset()..view.offset().checked_add(view.length())?));
                let got = match bytes {
                    Some(b) => Image::decode(&file, b),
                    None => Err("lies outside its buffer".into()),
                };
                (file, got)
            }
        }
    }
}

/// Whether an accessor holds what glTF 2.0 allows there (the crate's
/// reader asserts its types, a panic, and reaches `unreachable!()` on
/// other index types): POSITION VEC3 of float, or with
/// `KHR_mesh_quantization` of (unsigned) byte or short, normalized or not;
/// NORMAL VEC3 of float or of normalized byte or short; indices SCALAR of
/// unsigned byte, short or int.
fn check_accessor_type(what: &str, acc: &gltf::Accessor) -> Result<(), String> {
    use gltf::accessor::{DataType, Dimensions};
    let (dims, ty) = (acc.dimensions(), acc.data_type());
    let ok = match what {
        "indices" => {
            dims == Dimensions::Scalar && matches!(ty, DataType::U8 | DataType::U16 | DataType::U32)
        }
        "POSITION" => dims == Dimensions::Vec3 && ty != DataType::U32,
        // What the crate's readers take (others are `unreachable!()` there).
        "TEXCOORD_0" | "TEXCOORD_1" => {
            dims == Dimensions::Vec2 && matches!(ty, DataType::F32 | DataType::U8 | DataType::U16)
        }
        "COLOR_0" => {
            matches!(dims, Dimensions::Vec3 | Dimensions::Vec4)
                && matches!(ty, DataType::F32 | DataType::U8 | DataType::U16)
        }
        _ => {
            dims == Dimensions::Vec3
                && (ty == DataType::F32
                    || acc.normalized() && matches!(ty, DataType::I8 | DataType::I16))
        }
    };
    if ok {
        return Ok(());
    }
    let expected = match what {
        "indices" => "SCALAR of unsigned byte, short or int",
        "POSITION" => {
            "VEC3 of float, or (KHR_mesh_quantization) of byte, unsigned byte, short or unsigned short"
        }
        "TEXCOORD_0" | "TEXCOORD_1" => {
            "VEC2 of float, or of normalized unsigned byte or unsigned short"
        }
        "COLOR_0" => "VEC3 or VEC4 of float, or of normalized unsigned byte or unsigned short",
        _ => "VEC3 of float, or (KHR_mesh_quantization) of normalized byte or short",
    };
    Err(format!(
        "{what} accessor {} holds {} of {}{}, expected {expected}",
        acc.index(),
        dims_name(dims),
        if acc.normalized() { "normalized " } else { "" },
        type_name(ty)
    ))
}

fn dims_name(d: gltf::accessor::Dimensions) -> &'static str {
    use gltf::accessor::Dimensions::*;
    match d {
        Scalar => "SCALAR",
        Vec2 => "VEC2",
        Vec3 => "VEC3",
        Vec4 => "VEC4",
        Mat2 => "MAT2",
        Mat3 => "MAT3",
        Mat4 => "MAT4",
    }
}

fn type_name(t: gltf::accessor::DataType) -> &'static str {
    use gltf::accessor::DataType::*;
    match t {
        I8 => "signed byte",
        U8 => "unsigned byte",
        I16 => "short",
        U16 => "unsigned short",
        U32 => "unsigned int",
        F32 => "float",
    }
}

/// Whether an accessor's data lies inside its buffers as declared: views
/// inside their buffers, strides at least one element, `count` elements
/// inside the view; sparse parts likewise, and a sparse accessor without a
/// view no longer than its buffers could describe.
fn check_accessor(acc: &gltf::Accessor, buffers: &[Vec<u8>]) -> Result<(), String> {
    let name = format!("accessor {}", acc.index());
    let count = acc.count() as u64;
    let elem = acc.size() as u64;
    let view_len = |v: &gltf::buffer::View| -> Result<u64, String> {
        let buf = buffers
            .get(v.buffer().index())
            .ok_or_else(|| format!("{name}: buffer {} does not exist", v.buffer().index()))?;
        let end = v.offset() as u64 + v.length() as u64;
        if end > buf.len() as u64 {
            return Err(format!(
                "{name}: buffer view {} ends at byte {end}, past its buffer's {} bytes",
                v.index(),
                buf.len()
            ));
        }
        Ok(v.length() as u64)
    };
    // The crate's reader computes `count - 1` (and `sparse count - 1`):
    // an overflow for the 0 that the format does not allow.
    if count == 0 {
        return Err(format!(
            "{name}: count 0 (an accessor has at least 1 element)"
        ));
    }
    if acc.sparse().is_some_and(|sp| sp.count() == 0) {
        return Err(format!("{name}: sparse count 0 (at least 1 value)"));
    }
    let total: u64 = buffers.iter().map(|b| b.len() as u64).sum();
    match acc.view() {
        Some(v) => {
            let len = view_len(&v)?;
            let stride = v.stride().map_or(elem, |s| s as u64);
            if stride < elem {
                return Err(format!(
                    "{name}: byteStride {stride} is smaller than its {elem}-byte elements"
                ));
            }
            let need = acc.offset() as u64 + (count - 1) * stride + elem;
            if need > len {
                return Err(format!(
                    "{name}: {count} elements need {need} bytes, its buffer view has {len}"
                ));
            }
        }
        // All zeros but for sparse values: bounded by what the file holds.
        None if count > 16 * total + 65536 => {
            return Err(format!(
                "{name}: {count} elements without data in a file of {total} buffer bytes"
            ));
        }
        None => {}
    }
    if let Some(sp) = acc.sparse() {
        let n = sp.count() as u64;
        if n > count {
            return Err(format!("{name}: {n} sparse values for {count} elements"));
        }
        let index_size = match sp.indices().index_type() {
            gltf::accessor::sparse::IndexType::U8 => 1,
            gltf::accessor::sparse::IndexType::U16 => 2,
            gltf::accessor::sparse::IndexType::U32 => 4,
        };
        for (what, v, offset, size) in [
            (
                "indices",
                sp.indices().view(),
                sp.indices().offset(),
                index_size,
            ),
            ("values", sp.values().view(), sp.values().offset(), elem),
        ] {
            let len = view_len(&v)?;
            // The crate steps through sparse data by the view's stride
            // (the format says these views have none) and panics reading
            // an element from a step shorter than it.
            let stride = v.stride().map_or(size, |s| s as u64);
            if stride < size {
                return Err(format!(
                    "{name}: sparse {what}: buffer view {} has byteStride {stride}, smaller than its {size}-byte elements (sparse data is tightly packed: no byteStride)",
                    v.index()
                ));
            }
            let need = offset as u64 + (n - 1) * stride + size;
            if need > len {
                return Err(format!(
                    "{name}: {n} sparse {what} need {need} bytes, their buffer view has {len}"
                ));
            }
        }
    }
    Ok(())
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = (b[i] == b'%' && i + 2 < b.len())
            .then(|| {
                std::str::from_utf8(&b[i + 1..i + 3])
                    .ok()
                    .and_then(|h| u8::from_str_radix(h, 16).ok())
            })
            .flatten();
        if let Some(v) = hex {
            out.push(v);
            i += 3;
            continue;
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}
