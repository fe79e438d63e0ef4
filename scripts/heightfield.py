#!/usr/bin/env python3
"""A heightfield glTF of about N triangles, for docs/meshes.md's "Big
scenes: memory per triangle" (the file is generated, not committed).

    scripts/heightfield.py TRIANGLES OUT.gltf

A square grid of k x k vertices (2 (k-1)^2 triangles), heights from a few
sines, with vertex normals (so smooth shading, the costlier case), one
node and no material: positions and normals as f32, indices as u32 in
OUT.bin beside it. Without numpy (the GPU machine), the same file from
plain Python, slower (about a minute for 10 M triangles)."""
import json
import math
import struct
import sys
from pathlib import Path

try:
    import numpy as np
except ImportError:
    np = None


def arrays_plain(k):
    """Positions, normals and indices as bytes, and the positions' bounds,
    as the numpy path computes them (f64, then f32)."""
    from array import array
    pos, nor = array("f"), array("f")
    for ix in range(k):
        x = -1.0 + 2.0 * ix / (k - 1)
        for iz in range(k):
            z = -1.0 + 2.0 * iz / (k - 1)
            h = 0.08 * math.sin(9 * x) * math.cos(7 * z) + 0.03 * math.sin(31 * x + 17 * z)
            dx = 0.08 * 9 * math.cos(9 * x) * math.cos(7 * z) + 0.03 * 31 * math.cos(31 * x + 17 * z)
            dz = -0.08 * 7 * math.sin(9 * x) * math.sin(7 * z) + 0.03 * 17 * math.cos(31 * x + 17 * z)
            ln = math.sqrt(dx * dx + 1.0 + dz * dz)
            pos.extend((x, h, z))
            nor.extend((-dx / ln, 1.0 / ln, -dz / ln))
    idx = array("I")
    for i in range(k - 1):
        for j in range(k - 1):
            a = i * k + j
            b, c, d = a + k, a + k + 1, a + 1
            idx.extend((a, d, c, a, c, b))
    lo = [min(pos[a::3]) for a in range(3)]
    hi = [max(pos[a::3]) for a in range(3)]
    return pos.tobytes(), nor.tobytes(), idx.tobytes(), len(pos) // 3, len(idx), lo, hi


def main():
    want, out = int(sys.argv[1]), Path(sys.argv[2])
    k = int(math.sqrt(want / 2)) + 1
    if np is None:
        p, n, i, nv, ni, lo, hi = arrays_plain(k)
        write(out, p + n + i, nv, ni, lo, hi)
        return
    u = np.linspace(-1.0, 1.0, k, dtype=np.float64)
    x, z = np.meshgrid(u, u, indexing="ij")
    h = 0.08 * np.sin(9 * x) * np.cos(7 * z) + 0.03 * np.sin(31 * x + 17 * z)
    dx = 0.08 * 9 * np.cos(9 * x) * np.cos(7 * z) + 0.03 * 31 * np.cos(31 * x + 17 * z)
    dz = -0.08 * 7 * np.sin(9 * x) * np.sin(7 * z) + 0.03 * 17 * np.cos(31 * x + 17 * z)
    pos = np.stack([x, h, z], -1).reshape(-1, 3).astype(np.float32)
    n = np.stack([-dx, np.ones_like(dx), -dz], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    nor = n.reshape(-1, 3).astype(np.float32)
    i = np.arange(k - 1)
    a = (i[:, None] * k + i[None, :]).reshape(-1).astype(np.uint32)
    b, c, d = a + k, a + k + 1, a + 1
    # Counter-clockwise seen from +y.
    idx = np.stack([a, d, c, a, c, b], -1).reshape(-1).astype(np.uint32)
    blob = pos.tobytes() + nor.tobytes() + idx.tobytes()
    write(out, blob, len(pos), len(idx), pos.min(0).tolist(), pos.max(0).tolist())


def write(out, blob, nv, ni, lo, hi):
    out.with_suffix(".bin").write_bytes(blob)
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2}]}],
        "buffers": [{"uri": out.with_suffix(".bin").name, "byteLength": len(blob)}],
        "bufferViews": [
            {"buffer": 0, "byteLength": nv * 12},
            {"buffer": 0, "byteOffset": nv * 12, "byteLength": nv * 12},
            {"buffer": 0, "byteOffset": nv * 24, "byteLength": ni * 4},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": nv, "type": "VEC3",
             "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": nv, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5125, "count": ni, "type": "SCALAR"},
        ],
    }
    out.write_text(json.dumps(doc))
    print(f"{out}: {ni // 3} triangles, {nv} vertices")


if __name__ == "__main__":
    main()
