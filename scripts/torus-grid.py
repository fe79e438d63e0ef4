#!/usr/bin/env python3
"""One 19,800-triangle torus placed by N nodes, as tests/instancing.rs
makes it: `torus-grid.py OUT.gltf N [copied]` writes OUT.gltf and
OUT.bin. Nodes on a grid 3 apart (ceil(N^(1/3)) a side), each turned about
y; `copied` gives each node a mesh entry of its own over the same data,
which the loader copies (the one-level form)."""
import json, math, struct, sys

out, n = sys.argv[1], int(sys.argv[2])
copied = len(sys.argv) > 3 and sys.argv[3] == "copied"
maj, mnr = 110, 90
pos = []
for i in range(maj):
    a = 2 * math.pi * i / maj
    for j in range(mnr):
        b = 2 * math.pi * j / mnr
        r = 1 + 0.35 * math.cos(b)
        pos += [r * math.cos(a), 0.35 * math.sin(b), r * math.sin(a)]
idx = []
for i in range(maj):
    for j in range(mnr):
        at = lambda i, j: (i % maj) * mnr + j % mnr
        a, b, c, d = at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)
        idx += [a, b, c, a, c, d]
data = struct.pack(f"<{len(pos)}f", *pos) + struct.pack(f"<{len(idx)}I", *idx)
bin_name = out.rsplit("/", 1)[-1].replace(".gltf", ".bin")
open(out.replace(".gltf", ".bin"), "wb").write(data)
side = max(1, math.ceil(round(n ** (1 / 3), 9)))
nodes = []
for k in range(n):
    x, y, z = k // (side * side), (k // side) % side, k % side
    h = 0.05 * k
    nodes.append({"mesh": k if copied else 0, "translation": [3.0 * x, 3.0 * y, 3.0 * z],
                  "rotation": [0.0, math.sin(h), 0.0, math.cos(h)]})
prim = {"attributes": {"POSITION": 0}, "indices": 1}
nv, ni = len(pos) // 3, len(idx)
json.dump({
    "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": list(range(n))}],
    "nodes": nodes, "meshes": [{"primitives": [prim]}] * (n if copied else 1),
    "buffers": [{"uri": bin_name, "byteLength": len(data)}],
    "bufferViews": [{"buffer": 0, "byteLength": nv * 12},
                    {"buffer": 0, "byteOffset": nv * 12, "byteLength": ni * 4}],
    "accessors": [{"bufferView": 0, "componentType": 5126, "count": nv, "type": "VEC3"},
                  {"bufferView": 1, "componentType": 5125, "count": ni, "type": "SCALAR"}],
}, open(out, "w"))
