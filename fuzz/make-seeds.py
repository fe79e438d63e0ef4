#!/usr/bin/env python3
"""Writes fuzz/seeds/ (the seed corpora committed with the fuzz targets) from
the repository's examples and small hand-written cases. Run from anywhere;
the output is deterministic."""
import base64, gzip, json, os, shutil, struct

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEEDS = os.path.join(ROOT, "fuzz", "seeds")
EX = os.path.join(ROOT, "examples")


def put(target, name, data):
    if isinstance(data, str):
        data = data.encode()
    with open(os.path.join(SEEDS, target, name), "wb") as f:
        f.write(data)


def read(*p):
    with open(os.path.join(EX, *p), "rb") as f:
        return f.read()


for t in ["scene_toml", "obj_mtl", "gltf", "ply", "film_codec"]:
    shutil.rmtree(os.path.join(SEEDS, t), ignore_errors=True)
    os.makedirs(os.path.join(SEEDS, t))

# Scenes: the examples (they name models/cornell_box.obj and models/Box.gltf,
# which the target's bundle holds) and one of each object kind.
for name in ["cornell.toml", "animation.toml", "showcase.toml", "depth.toml", "resolution.toml"]:
    put("scene_toml", name, read(name))
for name in ["hard/nested-glass.toml", "hard/huge-floor.toml", "complexity/glass-3.toml"]:
    put("scene_toml", name.replace("/", "-"), read(name))
put("scene_toml", "box-gltf-ply.toml", """[render]
width = 8
height = 8
[camera]
position = [0.0, 0.0, -5.0]
look_at = [0.0, 0.0, 0.0]
fov_y = 40.0
[[objects]]
type = "mesh"
path = "models/Box.gltf"
[[objects]]
type = "mesh"
path = "tri.ply"
material = { diffuse = [0.5, 0.5, 0.5] }
""")

# OBJ: the OBJ, a NUL, then its MTL library.
put("obj_mtl", "cornell", read("models", "cornell_box.obj") + b"\0" + read("models", "cornell_box.mtl"))
put("obj_mtl", "quad-shiny", b"mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 2\nusemtl shiny\nf 1//1 2//1 3//1 4//1\n\0"
    b"newmtl shiny\nKa 0.1 0.2 0.3\nKd 0.5 0.6 0.7\nKs 0.9 0.9 0.9\nNs 64\nd 0.25\nNi 1.5\nillum 3\n")
put("obj_mtl", "grey-kd", b"mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl g\nf 1 2 3\n\0newmtl g\nKd 0.5\nKs 1\nTr 0.5\n")
put("obj_mtl", "groups-uv", b"o a\ng b\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\n"
    b"s 1\nf 1/1/1 2/2/1 3/3/1\nf -1 -2 -3\nl 1 2\np 1\nf 1/1 2/2 4/3\n")
put("obj_mtl", "no-mtl", b"mtllib gone.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")

# glTF: Box (embedded buffer), the same as GLB, and small hand-written cases.
box = json.loads(read("models", "Box.gltf"))
put("gltf", "Box.gltf", read("models", "Box.gltf"))
uri = box["buffers"][0]["uri"]
binary = base64.b64decode(uri.split(";base64,", 1)[1])
glb_json = dict(box)
glb_json["buffers"] = [{"byteLength": len(binary)}]


def glb(doc, binary):
    j = json.dumps(doc, separators=(",", ":")).encode()
    j += b" " * (-len(j) % 4)
    b = binary + b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<II", len(j), 0x4E4F534A) + j + struct.pack("<II", len(b), 0x004E4942) + b
    return b"glTF" + struct.pack("<II", 2, 12 + len(chunks)) + chunks


put("gltf", "Box.glb", glb(glb_json, binary))
tri = b"".join(struct.pack("<3f", *v) for v in [(0, 0, 0), (1, 0, 0), (0, 1, 0)])
tri_uri = "data:application/octet-stream;base64," + base64.b64encode(tri).decode()


def tri_gltf(accessor, view='{"buffer":0,"byteLength":36}', extra=""):
    return ('{"asset":{"version":"2.0"},"buffers":[{"byteLength":36,"uri":"%s"}],"bufferViews":[%s],'
            '"accessors":[%s],"meshes":[{"primitives":[{"attributes":{"POSITION":0}%s}]}]}' % (tri_uri, view, accessor, extra))


acc = '{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}'
put("gltf", "tri.gltf", tri_gltf(acc))
put("gltf", "tri-strip.gltf", tri_gltf(acc, extra=',"mode":5'))
put("gltf", "tri-sparse.gltf", tri_gltf(
    '{"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0],"sparse":{"count":1,'
    '"indices":{"bufferView":0,"componentType":5125},"values":{"bufferView":0}}}'))
put("gltf", "tri-file-buffer.gltf", tri_gltf(acc).replace(tri_uri, "m.bin"))
put("gltf", "tri-nodes.gltf", tri_gltf(acc).rstrip("}") +
    ',"scene":0,"scenes":[{"nodes":[0]}],"nodes":[{"children":[1],"scale":[1,-1,1]},{"mesh":0,"translation":[1,2,3]}],'
    '"materials":[{"name":"m","pbrMetallicRoughness":{"baseColorFactor":[1,0,0,0.5],"metallicFactor":0.5,"roughnessFactor":0.2},"alphaMode":"BLEND"}]}')
put("gltf", "tri.glb", glb({"asset": {"version": "2.0"}, "buffers": [{"byteLength": 36}],
                            "bufferViews": [{"buffer": 0, "byteLength": 36}],
                            "accessors": [json.loads(acc)],
                            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}]}, tri))

# PLY: a mode byte (0 plain, 1 gzipped by the target, 2 gzip in the input), then the file.
head = ("ply\nformat {fmt} 1.0\ncomment seed\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\nproperty uchar red\n"
        "element face 2\nproperty list uchar int vertex_indices\nelement edge 1\nproperty int a\nproperty list uchar float junk\nend_header\n")
verts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
ascii_ply = head.format(fmt="ascii") + "".join("%g %g %g 0 0 1 %d\n" % (*v, i) for i, v in enumerate(verts)) + \
    "3 0 1 2\n3 0 2 3\n7 2 1.5 2.5\n"
put("ply", "ascii", b"\0" + ascii_ply.encode())
put("ply", "ascii-gz-by-target", b"\1" + ascii_ply.encode())
put("ply", "ascii-gz", b"\2" + gzip.compress(ascii_ply.encode(), mtime=0))
for fmt, e in [("binary_little_endian", "<"), ("binary_big_endian", ">")]:
    body = b"".join(struct.pack(e + "6fB", *v, 0, 0, 1, i) for i, v in enumerate(verts))
    body += struct.pack(e + "B3i", 3, 0, 1, 2) + struct.pack(e + "B3i", 3, 0, 2, 3)
    body += struct.pack(e + "iB2f", 7, 2, 1.5, 2.5)
    put("ply", fmt, b"\0" + head.format(fmt=fmt).encode() + body)
put("ply", "quad-double-uint", b"\0" + b"ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\n"
    b"property double z\nelement face 1\nproperty list ushort uint vertex_index\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")

# Films: mode, x, y, width, height, split, sums, counts (see fuzz_targets/film_codec.rs).
for name, (x, y, w, h) in {"2x3": (2, 3, 3, 2), "1x1": (0, 0, 1, 1), "empty": (5, 5, 0, 7)}.items():
    n = w * h
    sums = b"".join(struct.pack("<3Q", i, 2**64 - 1 - i, 1 << 40) for i in range(n))
    counts = b"".join(struct.pack("<I", i * 7) for i in range(n))
    put("film_codec", name, struct.pack("<B4IH", 1, x, y, w, h, len(sums)) + sums + counts)
put("film_codec", "large-rect", struct.pack("<B4IH", 0, 0, 0, 0xFFFFFFFF, 0xFFFFFFFF, 24) + b"\0" * 28)
