"""The rule of issue "Printable" for extrusion in mid-air, written for the
tests and the bench independently of the slicers (its own G-code parser,
samples and a k-d tree; it does not call :mod:`ambots.support` or
:mod:`ambots.overhang`).

* Extrusions are grouped into layers by height: layer k holds the moves
  whose z lies in (z_(k-1), z_k] of the nominal grid (first layer
  ``first_mm`` thick, then ``layer_mm``), so a support contact printed a
  little below its layer's top belongs to that layer.
* Every extruding move is sampled every <= ``step`` mm; a sample of layer
  k > 0 is supported when some sample of layer k - 1 (either end of every
  piece, so no gap in it exceeds ``step``) lies within one bead width.
* A run of unsupported samples along one path (consecutive extruding moves,
  end to start) at most ``bridge_mm`` long with supported samples on both
  sides is a bridge and counts as supported.
* share = unsupported length / extruded length.  Millimetres.
"""
import math
import re

import numpy as np
from scipy.spatial import cKDTree

_WORD = re.compile(r"([XYZEF])(-?\d*\.?\d+)")


def extrusion_paths(text):
    """Extruding paths of a G-code text (absolute XYZ, relative E, as both
    slicers write it here): list of (z, (n, 2) xy points)."""
    x = y = z = 0.0
    paths, cur = [], None
    for line in text.splitlines():
        line = line.split(";", 1)[0].strip()
        if not line.startswith(("G1 ", "G0 ")):
            continue
        w = dict((k, float(v)) for k, v in _WORD.findall(line))
        nx, ny, nz = w.get("X", x), w.get("Y", y), w.get("Z", z)
        moving = nx != x or ny != y
        if moving and w.get("E", 0.0) > 0 and nz == z:
            if cur is None or cur[0] != z:
                cur = (z, [(x, y)])
                paths.append(cur)
            cur[1].append((nx, ny))
        elif moving or nz != z:
            cur = None
        x, y, z = nx, ny, nz
    return [(zz, np.array(pts)) for zz, pts in paths]


def _samples(pts, step):
    """Midpoints of equal pieces <= step of a polyline, their lengths, and
    the pieces' ends."""
    a, b = pts[:-1], pts[1:]
    L = np.hypot(*(b - a).T)
    k = np.maximum(1, np.ceil(L / step)).astype(int)
    seg = np.repeat(np.arange(len(a)), k)
    j = np.arange(len(seg)) - np.repeat(np.cumsum(k) - k, k)
    f0, f1 = j / k[seg], (j + 1) / k[seg]
    p0 = a[seg] + (b[seg] - a[seg]) * f0[:, None]
    p1 = a[seg] + (b[seg] - a[seg]) * f1[:, None]
    return (p0 + p1) / 2.0, (L / k)[seg], np.concatenate([p0, p1])


def unsupported_share(text, layer_mm=0.2, first_mm=0.2, bead_mm=0.45, bridge_mm=10.0, step=0.2):
    """(share, unsupported mm, extruded mm) of a G-code text by the rule above."""
    layers = {}
    for z, pts in extrusion_paths(text):
        k = max(0, int(math.ceil((z - first_mm) / layer_mm - 1e-6)))
        layers.setdefault(k, []).append(_samples(pts, step))
    total = lost = 0.0
    for k in sorted(layers):
        paths = layers[k]
        total += sum(float(w.sum()) for _, w, _ in paths)
        if k == 0:
            continue
        below = layers.get(k - 1)
        if not below:
            lost += sum(float(w.sum()) for _, w, _ in paths)
            continue
        tree = cKDTree(np.concatenate([e for _, _, e in below]))
        for mid, w, _ in paths:
            d, _ = tree.query(mid, distance_upper_bound=bead_mm)
            ok = d <= bead_mm
            if ok.all():
                continue
            # runs of unsupported samples; a run with supported samples on both sides
            # and at most bridge_mm long is a bridge
            bad = np.concatenate([[False], ~ok, [False]]).astype(np.int8)
            starts = np.flatnonzero(np.diff(bad) == 1)
            ends = np.flatnonzero(np.diff(bad) == -1)
            cum = np.concatenate([[0.0], np.cumsum(w)])
            for s0, e0 in zip(starts, ends):
                run = cum[e0] - cum[s0]
                if s0 > 0 and e0 < len(ok) and run <= bridge_mm:
                    continue
                lost += run
    return (lost / total if total else 0.0), lost, total
