#!/usr/bin/env python3
"""A procedural equirectangular sky as an EXR file, for trying and timing
environment lighting (docs/path-tracing.md, "Environment") where no HDRI
may be downloaded: a blue-to-pale gradient above the horizon, a brown
ground below, and a sun of radius 2.5 degrees (radiance ~400) with a glow.
The mapping is Tessera's (Mitsuba's): d = (sin phi sin theta, cos theta,
-cos phi sin theta), phi = 2 pi u, theta = pi v.

    python3 scripts/sky-exr.py OUT.exr [WIDTH]      (numpy and mitsuba: scripts/test installs both)
"""
import sys

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")
out = sys.argv[1]
w = int(sys.argv[2]) if len(sys.argv) > 2 else 512
h = w // 2
theta = (np.arange(h) + 0.5) / h * np.pi
phi = (np.arange(w) + 0.5) / w * 2 * np.pi
t, p = np.meshgrid(theta, phi, indexing="ij")
d = np.stack([np.sin(p) * np.sin(t), np.cos(t), -np.cos(p) * np.sin(t)], -1)
up = d[..., 1]
sky = np.stack([0.25 + 0.5 * (1 - up), 0.45 + 0.4 * (1 - up), 0.95 - 0.1 * (1 - up)], -1)
img = np.where(up[..., None] > 0, sky, np.array([0.25, 0.2, 0.15]))
sun = np.array([0.5, 0.6, -0.62])
sun /= np.linalg.norm(sun)
c = (d * sun).sum(-1)
img = img + (c > np.cos(np.radians(2.5)))[..., None] * np.array([400.0, 360.0, 300.0])
img = img + np.exp((c - 1) * 40)[..., None] * np.array([2.0, 1.6, 1.0])
mi.Bitmap(img.astype(np.float32)).write(out)
