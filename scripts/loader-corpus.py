#!/usr/bin/env python3
"""Loader compatibility against a peer (issue 14).

For every OBJ, PLY (.ply, .ply.gz) and glTF (.gltf, .glb) file under a
corpus folder: asks the peer, trimesh, whether it loads the file to at
least one triangle; if it does, writes a small scene (a camera framing the
peer's bounds, one light, the model as a mesh object by absolute path) and
runs each given tessera binary on it:

    tessera render SCENE -o out.png --width 64 --height 48 --samples 1

with a 60 s timeout and a 4 GiB address-space cap (RLIMIT_AS, as
`ulimit -v`). Each binary renders every file the peer loads; files the
peer cannot load are listed but not rendered.

Writes OUT/loader-corpus.csv (one row per file and binary) and
OUT/summary.md (per format: files, peer loads, renders by each binary of
those the peer loads, and the failures with their first error line), and
prints the summary.

Usage:
    scripts/loader-corpus.py --make-plyfile-cases CORPUS/plyfile/generated
    scripts/loader-corpus.py CORPUS --bin before=/path/to/tessera \\
        --bin after=target/debug/tessera [--out DIR]

Needs trimesh and numpy (`pip install trimesh numpy`); trimesh reads glTF
without its optional extras. The peer runs in a child process per file
(same timeout and cap), so a peer crash or hang is that file's result.
"""

import argparse
import csv
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TIMEOUT_S = 60
ADDRESS_SPACE = 4 << 30
FORMATS = {".obj": "OBJ", ".ply": "PLY", ".gz": "PLY", ".gltf": "glTF", ".glb": "glTF"}


def model_format(path):
    name = path.name.lower()
    if name.endswith(".ply.gz"):
        return "PLY"
    return FORMATS.get(path.suffix.lower()) if path.suffix.lower() != ".gz" else None


def make_plyfile_cases(folder):
    """Writes the tetrahedron of python-plyfile's tests (test/test_plyfile.py,
    tet_ply) as plyfile writes it: ASCII and both byte orders, vertex
    coordinates in each of its scalar types, face lists with each count
    type, and the faces element before the vertices."""
    import numpy as np
    from plyfile import PlyData, PlyElement

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    coords = [(0, 0, 0), (0, 1, 1), (1, 0, 1), (1, 1, 0)]
    faces = [([0, 1, 2], 255, 255, 255), ([0, 2, 3], 255, 0, 0), ([0, 1, 3], 0, 255, 0), ([1, 2, 3], 0, 0, 255)]

    def tet(name, text, order, coord="f4", index="i4", count="u1", faces_first=False):
        vertex = np.array(coords, dtype=[(c, coord) for c in "xyz"])
        face = np.array(faces, dtype=[("vertex_indices", index, (3,)), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
        els = [PlyElement.describe(vertex, "vertex", comments=["tetrahedron vertices"]),
               PlyElement.describe(face, "face", len_types={"vertex_indices": count})]
        if faces_first:
            els.reverse()
        PlyData(els, text=text, byte_order=order, comments=["single tetrahedron with colored faces"]).write(
            str(folder / f"{name}.ply"))

    tet("tet_ascii", True, "=")
    tet("tet_binary_le", False, "<")
    tet("tet_binary_be", False, ">")
    for t in ["i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"]:
        tet(f"tet_coords_{t}", False, "<", coord=t)
    for t in ["u1", "u2", "u4", "i4"]:
        tet(f"tet_count_{t}", False, ">", count=t, index="u4")
    tet("tet_faces_first_ascii", True, "=", faces_first=True)
    tet("tet_faces_first_le", False, "<", faces_first=True)


def cap_memory():
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def peer_child(path):
    """Run in a child: print the peer's view of one file as JSON."""
    import numpy as np
    import trimesh

    out = {"triangles": 0, "bounds": None, "error": ""}
    try:
        loaded = trimesh.load(path, process=False)
        if isinstance(loaded, trimesh.Scene):
            meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        elif isinstance(loaded, trimesh.Trimesh):
            meshes = [loaded]
        else:
            meshes = []
            out["error"] = f"not a mesh: {type(loaded).__name__}"
        tris = sum(len(m.faces) for m in meshes)
        out["triangles"] = int(tris)
        if tris:
            verts = np.concatenate([m.vertices[m.faces.reshape(-1)] for m in meshes if len(m.faces)])
            verts = verts[np.all(np.isfinite(verts), axis=1)]
            if len(verts):
                out["bounds"] = [verts.min(axis=0).tolist(), verts.max(axis=0).tolist()]
        elif not out["error"]:
            out["error"] = "no triangles"
    except BaseException as e:  # the peer's refusal is a result
        out["error"] = f"{type(e).__name__}: {e}".splitlines()[0][:200]
    print(json.dumps(out))


def ask_peer(path):
    try:
        p = subprocess.run(
            [sys.executable, __file__, "--peer-child", str(path)],
            capture_output=True,
            text=True,
            timeout=TIMEOUT_S,
            preexec_fn=cap_memory,
        )
    except subprocess.TimeoutExpired:
        return {"triangles": 0, "bounds": None, "error": f"timeout after {TIMEOUT_S} s"}
    lines = [line for line in p.stdout.splitlines() if line.startswith("{")]
    if not lines:
        tail = (p.stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1]
        return {"triangles": 0, "bounds": None, "error": f"peer crashed: {tail[:200]}"}
    return json.loads(lines[-1])


def scene_toml(model, bounds):
    """A scene framing `bounds` (from the peer) with the model at its place."""
    lo, hi = bounds or ([-1.0] * 3, [1.0] * 3)
    centre = [(a + b) / 2 for a, b in zip(lo, hi)]
    radius = math.dist(lo, hi) / 2
    if not (math.isfinite(radius) and radius > 1e-9):
        radius = 1.0
    fov = 40.0
    dist = radius / math.sin(math.radians(fov / 2)) * 1.1
    eye = [centre[0] + 0.3 * dist, centre[1] + 0.4 * dist, centre[2] + 0.87 * dist]
    light = [centre[0] - 0.5 * dist, centre[1] + dist, centre[2] + dist]
    v = lambda p: "[" + ", ".join(f"{c:.9g}" for c in p) + "]"
    return f"""[render]
width = 64
height = 48
samples = 1
max_depth = 3

[camera]
position = {v(eye)}
look_at = {v(centre)}
fov_y = {fov}

[world]
ambient = [0.1, 0.1, 0.1]
background = [0.05, 0.1, 0.2]

[[lights]]
position = {v(light)}

[[objects]]
type = "mesh"
path = {json.dumps(str(model.resolve()))}
"""


def first_error(stderr):
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    for line in lines:
        if "error" in line.lower() or "panicked" in line:
            return line
    return lines[0] if lines else ""


def render(binary, scene, png):
    cmd = [str(binary), "render", str(scene), "-o", str(png), "--width", "64", "--height", "48", "--samples", "1"]
    start = time.monotonic()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S, preexec_fn=cap_memory)
    except subprocess.TimeoutExpired:
        return False, "timeout", f"timeout after {TIMEOUT_S} s", TIMEOUT_S
    secs = time.monotonic() - start
    ok = p.returncode == 0 and png.is_file()
    err = "" if ok else first_error(p.stderr) or f"exit {p.returncode}"
    return ok, p.returncode, err, secs


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("corpus", type=Path)
    ap.add_argument("--bin", action="append", required=True, metavar="LABEL=PATH",
                    help="a tessera binary to run, with a label for the tables (repeat)")
    ap.add_argument("--out", type=Path, default=Path("loader-corpus-out"))
    args = ap.parse_args()
    bins = []
    for b in args.bin:
        label, _, path = b.partition("=")
        if not path:
            label, path = Path(b).name, b
        bins.append((label, Path(path).resolve()))
    args.out.mkdir(parents=True, exist_ok=True)

    models = sorted(p for p in args.corpus.rglob("*") if p.is_file() and model_format(p))
    rows = []
    with tempfile.TemporaryDirectory(prefix="loader-corpus-") as tmp:
        tmp = Path(tmp)
        for i, model in enumerate(models):
            rel = model.relative_to(args.corpus)
            peer = ask_peer(model)
            peer_ok = peer["triangles"] > 0
            row = {"file": str(rel), "format": model_format(model), "peer_loads": int(peer_ok),
                   "peer_triangles": peer["triangles"], "peer_error": peer["error"]}
            scene = tmp / f"scene{i}.toml"
            scene.write_text(scene_toml(model, peer["bounds"]))
            for label, binary in bins:
                if peer_ok:
                    png = tmp / f"out{i}-{label}.png"
                    ok, rc, err, secs = render(binary, scene, png)
                else:
                    ok, rc, err, secs = False, "", "not run (the peer does not load it)", 0.0
                row.update({f"{label}_renders": int(ok), f"{label}_exit": rc,
                            f"{label}_error": err, f"{label}_seconds": f"{secs:.2f}"})
            rows.append(row)
            marks = " ".join(f"{label}={'ok' if row[f'{label}_renders'] else 'FAIL'}" for label, _ in bins)
            print(f"[{i + 1}/{len(models)}] {rel}: peer={'ok' if peer_ok else 'no'} {marks}", file=sys.stderr)

    with open(args.out / "loader-corpus.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)

    out = [f"# Loader corpus: {args.corpus}", "",
           "| format | files | peer loads | " + " | ".join(f"{label} renders" for label, _ in bins) + " |",
           "|---|---:|---:|" + "---:|" * len(bins)]
    fmts = ["OBJ", "PLY", "glTF"]
    for fmt in fmts + ["all"]:
        sel = [r for r in rows if fmt == "all" or r["format"] == fmt]
        loads = [r for r in sel if r["peer_loads"]]
        cells = [f"{sum(r[f'{label}_renders'] for r in loads)} / {len(loads)}" for label, _ in bins]
        out.append(f"| {fmt} | {len(sel)} | {len(loads)} | " + " | ".join(cells) + " |")
    for label, _ in bins:
        out += ["", f"## {label}: files the peer loads and tessera does not render", ""]
        fails = [r for r in rows if r["peer_loads"] and not r[f"{label}_renders"]]
        out += [f"- {r['file']} (exit {r[f'{label}_exit']}): {r[f'{label}_error']}" for r in fails] or ["- none"]
    out += ["", "## files the peer does not load", ""]
    out += [f"- {r['file']}: {r['peer_error']}" for r in rows if not r["peer_loads"]] or ["- none"]
    text = "\n".join(out) + "\n"
    (args.out / "summary.md").write_text(text)
    print(text)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--peer-child":
        peer_child(sys.argv[2])
    elif len(sys.argv) == 3 and sys.argv[1] == "--make-plyfile-cases":
        make_plyfile_cases(sys.argv[2])
    else:
        main()
