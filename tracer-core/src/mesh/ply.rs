//! PLY (Stanford polygon format): ASCII and binary (either byte order),
//! optionally gzipped (.ply.gz). Reads vertex x/y/z (and nx/ny/nz when all
//! present) and face `vertex_indices` (or `vertex_index`) lists, fan-splitting
//! polygons; other elements and properties are parsed and skipped.
//! The maintained PLY crates are either unmaintained or pull in far more
//! than this needs, and this reader gives errors with element and index.

use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use super::{Mesh, MeshError};

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
}

#[derive(Debug)]
enum Property {
    Scalar {
        name: String,
        ty: Scalar,
    },
    List {
        name: String,
        count: Scalar,
        item: Scalar,
    },
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    Little,
    Big,
}

/// Upper bound on any single polygon's vertex count (anything larger is corrupt).
const MAX_POLYGON: usize = 1 << 16;

pub(super) fn load(name: &str, bytes: &[u8]) -> Result<Mesh, MeshError> {
    let path = Path::new(name);
    let err = |m: String| MeshError::new(path, m);
    let file = bytes;
    let gz = name.to_lowercase().ends_with(".gz");
    let raw: Box<dyn Read + '_> = if gz {
        Box::new(flate2::read::GzDecoder::new(file))
    } else {
        Box::new(file)
    };
    let mut r = BufReader::with_capacity(1 << 16, raw);
    let (format, elements) = header(&mut r).map_err(|m| err(format!("invalid PLY header: {m}")))?;
    body(&mut r, format, &elements).map_err(|m| err(format!("invalid PLY: {m}")))
}

/// How header lines end, as the first line ends: `\n` (and `\r\n`) or a
/// lone `\r` (classic Mac OS writers). A binary body starts right after
/// `end_header`'s terminator, so it must be known, not guessed per line.
#[derive(Clone, Copy, PartialEq)]
enum LineEnd {
    Lf,
    Cr,
}

/// Reads one header line (at most 4096 bytes) ending with `end`, whose
/// terminator is kept; `None` for `end`: the first line, ending with `\n`,
/// `\r\n` or `\r`, and which of the two it was is returned.
fn header_line(
    r: &mut impl BufRead,
    line: &mut String,
    end: Option<LineEnd>,
) -> Result<LineEnd, String> {
    line.clear();
    let mut bytes = Vec::new();
    let found = loop {
        let buf = r.fill_buf().map_err(|e| e.to_string())?;
        if buf.is_empty() {
            return Err("file ends before end_header".into());
        }
        let stop = buf.iter().position(|&b| match end {
            Some(LineEnd::Lf) => b == b'\n',
            Some(LineEnd::Cr) => b == b'\r',
            None => b == b'\n' || b == b'\r',
        });
        let take = stop.map_or(buf.len(), |i| i + 1);
        let take = take.min(4096 - bytes.len());
        bytes.extend_from_slice(&buf[..take]);
        r.consume(take);
        match stop {
            Some(i) if i < take => break bytes[bytes.len() - 1],
            _ if bytes.len() >= 4096 => break b'\n',
            _ => {}
        }
    };
    let ending = match (end, found) {
        (Some(e), _) => e,
        (None, b'\r') => {
            // `\r\n` is a `\n` ending with a `\r` that trimming removes.
            if r.fill_buf().map_err(|e| e.to_string())?.first() == Some(&b'\n') {
                bytes.push(b'\n');
                r.consume(1);
                LineEnd::Lf
            } else {
                LineEnd::Cr
            }
        }
        (None, _) => LineEnd::Lf,
    };
    // Comments in other encodings (Latin-1 names) are no reason to refuse.
    line.push_str(&String::from_utf8_lossy(&bytes));
    Ok(ending)
}

fn header(r: &mut impl BufRead) -> Result<(Format, Vec<Element>), String> {
    let mut line = String::new();
    let ending = header_line(r, &mut line, None)?;
    let mut next = |line: &mut String| header_line(r, line, Some(ending)).map(|_| ());
    if line.trim_end() != "ply" {
        return Err("the file does not start with \"ply\"".into());
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    for lineno in 2.. {
        next(&mut line)?;
        let words: Vec<&str> = line.split_ascii_whitespace().collect();
        let bad = |what: &str| format!("line {lineno}: {what}: {:?}", line.trim_end());
        match words.as_slice() {
            ["end_header"] => break,
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["format", f, _version] => {
                format = Some(match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::Little,
                    "binary_big_endian" => Format::Big,
                    _ => return Err(bad("unknown format")),
                })
            }
            ["element", name, count] => elements.push(Element {
                name: name.to_string(),
                count: count.parse().map_err(|_| bad("bad element count"))?,
                props: Vec::new(),
            }),
            ["property", "list", c, i, name] => {
                let (Some(count), Some(item)) = (Scalar::parse(c), Scalar::parse(i)) else {
                    return Err(bad("unknown type"));
                };
                let el = elements
                    .last_mut()
                    .ok_or_else(|| bad("property before any element"))?;
                el.props.push(Property::List {
                    name: name.to_string(),
                    count,
                    item,
                });
            }
            ["property", t, name] => {
                let ty = Scalar::parse(t).ok_or_else(|| bad("unknown type"))?;
                let el = elements
                    .last_mut()
                    .ok_or_else(|| bad("property before any element"))?;
                el.props.push(Property::Scalar {
                    name: name.to_string(),
                    ty,
                });
            }
            _ => return Err(bad("unrecognised line")),
        }
    }
    Ok((format.ok_or("no format line")?, elements))
}

/// Reads values of one element instance, in ASCII or binary.
struct Values<'a, R: BufRead> {
    r: &'a mut R,
    format: Format,
    /// ASCII: the current line and how far it has been read.
    line: String,
    pos: usize,
}

impl<R: BufRead> Values<'_, R> {
    /// Ends an element instance: in ASCII each is one line, and values past
    /// the declared properties (writers add colours, alpha, ...) are skipped.
    /// Lines end with `\n`, `\r\n` or a lone `\r`: a body of `\r` lines is
    /// read as one string and its rows end at each `\r`.
    fn end_row(&mut self) {
        if self.format == Format::Ascii {
            let rest = &self.line[self.pos..];
            self.pos += rest.find(['\n', '\r']).map_or(rest.len(), |i| i + 1);
        }
    }

    fn next(&mut self, ty: Scalar) -> Result<f64, String> {
        if self.format == Format::Ascii {
            let tok = loop {
                let rest = &self.line[self.pos..];
                let start = rest.len() - rest.trim_start().len();
                let rest = &rest[start..];
                if !rest.is_empty() {
                    let len = rest
                        .find(|c: char| c.is_ascii_whitespace())
                        .unwrap_or(rest.len());
                    let tok = &rest[..len];
                    self.pos += start + len;
                    break tok;
                }
                self.line.clear();
                self.pos = 0;
                if self
                    .r
                    .read_line(&mut self.line)
                    .map_err(|e| e.to_string())?
                    == 0
                {
                    return Err("unexpected end of file".into());
                }
            };
            return tok
                .parse::<f64>()
                .map_err(|_| format!("not a number: {tok:?}"));
        }
        let mut b = [0u8; 8];
        let n = ty.size();
        self.r
            .read_exact(&mut b[..n])
            .map_err(|_| "unexpected end of file".to_string())?;
        if self.format == Format::Big {
            b[..n].reverse();
        }
        Ok(match ty {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::F64 => f64::from_le_bytes(b),
        })
    }
}

fn body(r: &mut impl BufRead, format: Format, elements: &[Element]) -> Result<Mesh, String> {
    let mut mesh = Mesh::default();
    let mut vals = Values {
        r,
        format,
        line: String::new(),
        pos: 0,
    };
    let mut vertex_seen = false;
    for el in elements {
        let scalar_index = |n: &str| {
            el.props
                .iter()
                .position(|p| matches!(p, Property::Scalar { name, .. } if name == n))
        };
        let mut row = vec![0.0f64; el.props.len()];
        let mut list: Vec<f64> = Vec::new();
        match el.name.as_str() {
            "vertex" => {
                vertex_seen = true;
                let (Some(x), Some(y), Some(z)) =
                    (scalar_index("x"), scalar_index("y"), scalar_index("z"))
                else {
                    return Err("element vertex lacks x, y or z".into());
                };
                let normal = match (scalar_index("nx"), scalar_index("ny"), scalar_index("nz")) {
                    (Some(a), Some(b), Some(c)) => Some([a, b, c]),
                    _ => None,
                };
                let cap = el.count.min(1 << 20);
                mesh.positions.reserve(cap);
                for i in 0..el.count {
                    read_row(&mut vals, el, &mut row, &mut list)
                        .map_err(|e| format!("vertex {i}: {e}"))?;
                    vals.end_row();
                    mesh.positions
                        .push([row[x] as f32, row[y] as f32, row[z] as f32]);
                    if let Some([a, b, c]) = normal {
                        mesh.normals
                            .push([row[a] as f32, row[b] as f32, row[c] as f32]);
                    }
                }
            }
            "face" => {
                // Faces may come before the vertices (some writers put them
                // first): their indices are then checked once all are read.
                let li = el
                    .props
                    .iter()
                    .position(|p| matches!(p, Property::List { name, .. } if name == "vertex_indices" || name == "vertex_index"))
                    .ok_or("element face has no vertex_indices list")?;
                mesh.triangles.reserve(el.count.min(1 << 20));
                let mut poly = Vec::new();
                for i in 0..el.count {
                    poly.clear();
                    read_face(&mut vals, el, li, &mut poly)
                        .map_err(|e| format!("face {i}: {e}"))?;
                    vals.end_row();
                    let nv = mesh.positions.len() as u32;
                    if let Some(&bad) = poly.iter().find(|&&v| vertex_seen && v >= nv) {
                        return Err(format!(
                            "face {i}: vertex index {bad} out of range ({nv} vertices)"
                        ));
                    }
                    for k in 2..poly.len() {
                        mesh.triangles.push([poly[0], poly[k - 1], poly[k]]);
                    }
                }
            }
            // No properties, no data: nothing to read, however large the count.
            _ if el.props.is_empty() => {}
            _ => {
                for i in 0..el.count {
                    read_row(&mut vals, el, &mut row, &mut list)
                        .map_err(|e| format!("{} {i}: {e}", el.name))?;
                    vals.end_row();
                }
            }
        }
    }
    mesh.triangle_materials = vec![0; mesh.triangles.len()];
    Ok(mesh)
}

/// Reads one element instance; scalars into `row`, lists skipped.
fn read_row<R: BufRead>(
    v: &mut Values<R>,
    el: &Element,
    row: &mut [f64],
    scratch: &mut Vec<f64>,
) -> Result<(), String> {
    for (k, p) in el.props.iter().enumerate() {
        match p {
            Property::Scalar { ty, .. } => row[k] = v.next(*ty)?,
            Property::List { count, item, .. } => {
                scratch.clear();
                let n = list_len(v.next(*count)?)?;
                for _ in 0..n {
                    scratch.push(v.next(*item)?);
                }
            }
        }
    }
    Ok(())
}

fn read_face<R: BufRead>(
    v: &mut Values<R>,
    el: &Element,
    list: usize,
    poly: &mut Vec<u32>,
) -> Result<(), String> {
    for (k, p) in el.props.iter().enumerate() {
        match p {
            Property::Scalar { ty, .. } => {
                v.next(*ty)?;
            }
            Property::List { count, item, .. } => {
                let n = list_len(v.next(*count)?)?;
                for _ in 0..n {
                    let x = v.next(*item)?;
                    if k == list {
                        if !(x >= 0.0 && x <= u32::MAX as f64 && x.fract() == 0.0) {
                            return Err(format!("bad vertex index {x}"));
                        }
                        poly.push(x as u32);
                    }
                }
            }
        }
    }
    Ok(())
}

fn list_len(n: f64) -> Result<usize, String> {
    if n >= 0.0 && n.fract() == 0.0 && (n as usize) <= MAX_POLYGON {
        Ok(n as usize)
    } else {
        Err(format!("bad list length {n}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(data: &[u8]) -> Result<Mesh, String> {
        let mut r = BufReader::new(data);
        let (f, els) = header(&mut r)?;
        body(&mut r, f, &els)
    }

    #[test]
    fn ascii_and_binary_quads_are_fan_split() {
        let ascii = b"ply\nformat ascii 1.0\ncomment x\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1\n1 0 0 2\n1 1 0 3\n0 1 0 4\n4 0 1 2 3\n";
        let m = parse(ascii).unwrap();
        assert_eq!(m.positions[2], [1.0, 1.0, 0.0]);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);

        let mut bin = b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n".to_vec();
        for v in [0.0f64, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 2.0, 0.5] {
            bin.extend(v.to_be_bytes());
        }
        bin.push(3);
        for i in [0u32, 1, 2] {
            bin.extend(i.to_be_bytes());
        }
        let m = parse(&bin).unwrap();
        assert_eq!(m.positions[2], [0.0, 2.0, 0.5]);
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
    }

    #[test]
    fn truncated_and_malformed_files_are_errors_with_the_place() {
        let head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
        let e = parse(format!("{head}0 0 0\n1 0 0\n").as_bytes()).unwrap_err();
        assert_eq!(e, "vertex 2: unexpected end of file");
        let e = parse(format!("{head}0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n").as_bytes()).unwrap_err();
        assert_eq!(e, "face 0: vertex index 9 out of range (3 vertices)");
        let e = parse(format!("{head}0 0 0\n1 0 x\n").as_bytes()).unwrap_err();
        assert_eq!(e, "vertex 1: not a number: \"x\"");
        let e = parse(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n")
            .unwrap_err();
        assert!(e.starts_with("line 4: unknown type"), "{e}");
        let e = parse(b"PLY\n").unwrap_err();
        assert!(e.contains("does not start with \"ply\""), "{e}");
    }
}
