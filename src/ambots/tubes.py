"""Shaded bead geometry for RViz: the beads an arm laid as tubes of
triangles, coloured per face by a fixed light.  No ROS here (the ROS layer,
:mod:`ambots.ros.firmware`, turns the arrays into ``TRIANGLE_LIST``
markers).

Why the shading is baked: RViz 1.14 draws a ``TRIANGLE_LIST`` marker
without normals (its material has lighting on but no diffuse colour, and
with per-vertex or per-face colours lighting off), so RViz itself would
draw every face of a bead in the same flat colour.  Here each face gets its
own colour instead: the arm's filament colour times ``ambient + (1 -
ambient) * max(0, n . light)`` for the face's outward normal ``n`` and a
fixed light direction in the world frame (:data:`LIGHT`, from above), so the
tops of the beads are bright, the faces sloping down are dark and the layers
of a wall show as stripes from any side.

Steps (all vectorised, no Python loop per bead):

1. :func:`merge_beads` -- consecutive beads that continue each other (same
   key, e.g. layer and G-code line; end of one = start of the next) and stay
   within ``tol_m`` of one straight chord become one segment, its area the
   volume-weighted mean (the firmware lays a G-code line as many short
   beads, one per waypoint: the demo's 55,790 beads per arm are 7,184
   segments).  Runs that leave the chord (arcs) are split where they leave
   it most (Douglas-Peucker, every run at once per pass).
2. :func:`tube_triangles` -- each segment as a tube of ``sides`` faces, two
   triangles per face (``2 * sides`` triangles a segment, no end caps; the
   next bead covers the joint): its cross-section a polygon inscribed in an
   ellipse, flattened so that it is exactly ``height`` tall (top on the
   nozzle path, bottom ``height`` below, as :mod:`ambots.deposit` lays its
   boxes) and has exactly the bead's cross-section ``area``.  With 6 sides
   (the default) it has a flat top and bottom and a point on each side,
   ``4/3`` of the box's width wide, so neighbouring beads overlap as real
   ones do.  Triangles are wound counter-clockwise seen from outside
   (``(b - a) x (c - a)`` points out).
3. :func:`face_normals`, :func:`shade` -- outward unit normals, colours.

:func:`bead_tubes` chains the three for one arm's beads.

:func:`exposed` tells which segments no camera outside the deposit can
see: the tubes are rasterised into cells (``cell`` across, one layer
high), the air connected to the outside of the grid is flood-filled (6
neighbours, by sweeps along the axes until nothing changes) and a segment
is exposed when one of its cells touches that air.  Beads buried inside the
part (infill under the top layers, the inner perimeters) are not; leaving
them out draws the same picture from outside with far fewer triangles
(the demo's finished part: about a fifth).  Air pockets narrower than a
cell count as closed.
"""
import numpy as np

from ambots.deposit import _frames

__all__ = ["LIGHT", "AMBIENT", "SIDES", "merge_beads", "section", "tube_triangles", "face_normals", "shade",
           "bead_tubes", "exposed"]

#: light direction in the world frame (towards the light): from above, a little from -x -y
LIGHT = np.array([-0.35, -0.45, 1.0]) / np.linalg.norm([-0.35, -0.45, 1.0])
#: brightness of a face turned away from the light (share of the full colour)
AMBIENT = 0.3
#: faces of a tube, around
SIDES = 6


def merge_beads(p0, p1, area, keys=(), tol_m=5e-5, join_m=1e-6, max_passes=64):
    """Merge consecutive beads into straight segments.

    ``p0``, ``p1`` (K, 3) m; ``area`` (K,) m^2; ``keys``: sequences of (K,)
    values that must be equal for two beads to merge (e.g. layer, G-code
    line).  Bead ``i`` continues bead ``i - 1`` when the keys agree and
    ``|p0[i] - p1[i-1]| <= join_m``; a run of continuing beads becomes one
    segment when every joint lies within ``tol_m`` of the segment from the
    run's first start to its last end, else it is split at the joint
    farthest from it, again until every part passes (at most
    ``max_passes`` times; what still fails stays unmerged).

    Returns ``(starts, ends, area, first)``: (M, 3), (M, 3), (M,) the
    length-weighted mean area (the volume is kept), and (M,) the index of
    each segment's first bead."""
    p0 = np.asarray(p0, dtype=float).reshape(-1, 3)
    p1 = np.asarray(p1, dtype=float).reshape(-1, 3)
    area = np.asarray(area, dtype=float).reshape(-1)
    K = len(p0)
    if K == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=int)
    cont = np.linalg.norm(p0[1:] - p1[:-1], axis=1) <= join_m
    for key in keys:
        key = np.asarray(key).reshape(-1)
        cont &= key[1:] == key[:-1]
    start = np.r_[True, ~cont]
    for _ in range(max_passes):
        first = np.nonzero(start)[0]
        last = np.r_[first[1:], K] - 1
        run = np.cumsum(start) - 1
        a, b = p0[first], p1[last]
        d = b - a
        L = np.linalg.norm(d, axis=1)
        u = d / np.where(L > 0, L, 1.0)[:, None]
        # distance of each bead's end (a joint, except for the run's last) to its run's chord
        x = p1 - a[run]
        dev = np.linalg.norm(x - np.sum(x * u[run], axis=1)[:, None] * u[run], axis=1)
        dev[last] = 0.0
        worst = np.maximum.reduceat(dev, first)
        bad = worst > tol_m
        if not bad.any():
            break
        # split each failing run after its farthest joint (the first one at the run's maximum)
        at = np.nonzero(bad[run] & (dev == worst[run]))[0]
        at = at[np.r_[True, run[at][1:] != run[at][:-1]]]
        start[at + 1] = True
    else:
        first = np.nonzero(start)[0]
        last = np.r_[first[1:], K] - 1
        run = np.cumsum(start) - 1
        x = p1 - p0[first][run]
        d = (p1[last] - p0[first])[run]
        u = d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
        dev = np.linalg.norm(x - np.sum(x * u, axis=1)[:, None] * u, axis=1)
        dev[last] = 0.0
        start[:] = start | (np.maximum.reduceat(dev, first) > tol_m)[run]     # leave those unmerged
    first = np.nonzero(start)[0]
    last = np.r_[first[1:], K] - 1
    lengths = np.linalg.norm(p1 - p0, axis=1)
    vol = np.add.reduceat(lengths * area, first)
    total = np.add.reduceat(lengths, first)
    mean_area = np.where(total > 0, vol / np.where(total > 0, total, 1.0), np.maximum.reduceat(area, first))
    return p0[first], p1[last], mean_area, first


def section(area, height, sides=SIDES):
    """Cross-section polygon(s): ``sides`` vertices (.., sides, 2) as (across,
    up) offsets from the centre, m, for beads of ``area`` (..) m^2 and
    ``height`` (..) m: vertex ``j`` at angle ``2 pi j / sides`` of an
    ellipse whose half-axes are chosen so that the polygon is ``height``
    tall and encloses ``area``."""
    if int(sides) != sides or sides < 3:
        raise ValueError("a tube needs at least 3 sides, got %r" % (sides,))
    sides = int(sides)
    theta = 2 * np.pi * np.arange(sides) / sides
    s_max = np.max(np.sin(theta))
    area, height = np.broadcast_arrays(np.asarray(area, dtype=float), np.asarray(height, dtype=float))
    b = height / (2 * s_max)                                   # half-axis up
    a = 2 * area / (sides * np.where(b > 0, b, 1.0) * np.sin(2 * np.pi / sides))    # half-axis across
    a = np.where(b > 0, a, 0.0)
    return np.stack([a[..., None] * np.cos(theta), b[..., None] * np.sin(theta)], axis=-1)


def tube_triangles(starts, ends, area, height, sides=SIDES):
    """Triangles (M * 2 * sides, 3, 3) of M segments' tubes, world frame m:
    segment ``i`` gives triangles ``2 * sides * i`` to ``2 * sides * (i +
    1) - 1``, face ``j`` (between section vertices ``j`` and ``j + 1``) as
    triangles ``2 j`` and ``2 j + 1``.  The tube's axis is the segment moved
    ``height / 2`` down (perpendicular to it, in its vertical plane), so its
    top touches the nozzle path.  ``area``, ``height``: (M,) or scalars."""
    starts = np.asarray(starts, dtype=float).reshape(-1, 3)
    ends = np.asarray(ends, dtype=float).reshape(-1, 3)
    M = len(starts)
    area = np.broadcast_to(np.asarray(area, dtype=float), (M,))
    height = np.broadcast_to(np.asarray(height, dtype=float), (M,))
    d = ends - starts
    u, w, v = _frames(d)
    sec = section(area, height, sides)                                    # (M, sides, 2)
    ring = sec[..., 0:1] * w[:, None, :] + (sec[..., 1:2] - height[:, None, None] / 2) * v[:, None, :]
    S = starts[:, None, :] + ring                                         # (M, sides, 3)
    E = ends[:, None, :] + ring
    S1, E1 = np.roll(S, -1, axis=1), np.roll(E, -1, axis=1)
    # (S_j, S_j+1, E_j+1) and (S_j, E_j+1, E_j): the section runs counter-clockwise about u, so out
    t1 = np.stack([S, S1, E1], axis=2)
    t2 = np.stack([S, E1, E], axis=2)
    return np.stack([t1, t2], axis=2).reshape(M * 2 * sides, 3, 3)


def face_normals(triangles):
    """Unit normals (T, 3) of triangles (T, 3, 3) by their winding:
    ``(b - a) x (c - a)``; degenerate triangles get (0, 0, 0)."""
    t = np.asarray(triangles, dtype=float)
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    L = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(L > 0, n / np.where(L > 0, L, 1.0), 0.0)


def shade(normals, colour, light=LIGHT, ambient=AMBIENT):
    """RGBA (T, 4) in 0..1 per face: ``colour`` (RGB or RGBA, 0..1) times
    ``ambient + (1 - ambient) * max(0, n . light)``; alpha kept."""
    c = np.asarray(colour, dtype=float).reshape(-1)
    rgba = np.append(c, 1.0)[:4] if len(c) == 3 else c[:4]
    light = np.asarray(light, dtype=float)
    light = light / np.linalg.norm(light)
    k = ambient + (1.0 - ambient) * np.clip(np.asarray(normals, dtype=float) @ light, 0.0, 1.0)
    out = np.empty((len(k), 4))
    out[:, :3] = k[:, None] * rgba[None, :3]
    out[:, 3] = rgba[3]
    return out


def bead_tubes(p0, p1, area, height, colour, keys=(), sides=SIDES, light=LIGHT, ambient=AMBIENT):
    """One arm's beads -> (triangles (T, 3, 3), face colours (T, 4)): merged
    (:func:`merge_beads`; beads of no area are left out), as tubes, shaded."""
    p0 = np.asarray(p0, dtype=float).reshape(-1, 3)
    p1 = np.asarray(p1, dtype=float).reshape(-1, 3)
    area = np.asarray(area, dtype=float).reshape(-1)
    keep = area > 0
    keys = [np.asarray(k).reshape(-1)[keep] for k in keys]
    s, e, a, _ = merge_beads(p0[keep], p1[keep], area[keep], keys)
    tris = tube_triangles(s, e, a, height, sides)
    return tris, shade(face_normals(tris), colour, light, ambient)


def _sweep(air, out, axis):
    """``out`` grown along ``axis``: every straight run of air cells that
    holds an ``out`` cell becomes ``out``."""
    a = np.moveaxis(air, axis, -1)
    o = np.moveaxis(out, axis, -1)
    rows = a.reshape(-1, a.shape[-1])
    start = rows.copy()
    start[:, 1:] &= ~rows[:, :-1]                       # an air cell after a solid one (or a row's first)
    run = np.cumsum(start.ravel()) - 1
    flat_air = rows.ravel()
    has = np.zeros(max(int(run[-1]) + 1, 1) if len(run) else 1, dtype=bool)
    has[run[(o.reshape(rows.shape).ravel()) & flat_air]] = True
    grown = flat_air & has[np.maximum(run, 0)]
    return np.moveaxis(grown.reshape(a.shape), -1, axis)


def exposed(starts, ends, area, height, cell=0.4e-3, floor_z=None, sides=SIDES, max_rounds=100):
    """(M,) bool: the segments' tubes (:func:`tube_triangles`) that touch
    air connected to the outside (see the module docstring).  ``height``:
    scalar layer height (m), the cells' height; ``cell``: their size across
    (m); ``floor_z``: cells whose centre is below it are solid (the bed's
    top: nothing is seen from under the bed), None: open below too."""
    starts = np.asarray(starts, dtype=float).reshape(-1, 3)
    ends = np.asarray(ends, dtype=float).reshape(-1, 3)
    M = len(starts)
    if M == 0:
        return np.zeros(0, dtype=bool)
    area = np.broadcast_to(np.asarray(area, dtype=float), (M,))
    h = float(height)
    half = section(area, h, sides)[:, :, 0].max(axis=1) * 0.8         # inside the tube's half-width
    d = ends - starts
    L = np.linalg.norm(d, axis=1)
    _, w, v = _frames(d)
    n = np.ceil(L / (cell / 2)).astype(int) + 1                        # samples along, <= cell/2 apart
    seg = np.repeat(np.arange(M), n)
    first = np.cumsum(n) - n
    t = (np.arange(len(seg)) - first[seg]) / np.maximum(n[seg] - 1, 1)
    centre = starts[seg] + t[:, None] * d[seg] - (h / 2) * v[seg]
    pts = np.concatenate([centre + (f * half[seg])[:, None] * w[seg] for f in (-1.0, 0.0, 1.0)])
    seg = np.tile(seg, 3)
    size = np.array([cell, cell, h])
    lo = pts.min(axis=0) - 2.5 * size            # a layer's centres in the middle of its cells
    shape = np.floor((pts.max(axis=0) + 2 * size - lo) / size).astype(int) + 1
    idx = np.floor((pts - lo) / size).astype(int)
    solid = np.zeros(shape, dtype=bool)
    solid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    if floor_z is not None:
        zc = lo[2] + (np.arange(shape[2]) + 0.5) * h
        solid[:, :, zc < floor_z] = True
    air = ~solid
    out = np.zeros(shape, dtype=bool)                                  # seeds: the grid's faces
    out[[0, -1], :, :] = out[:, [0, -1], :] = out[:, :, [0, -1]] = True
    out &= air
    count = int(out.sum())
    for _ in range(max_rounds):
        for axis in range(3):
            out = _sweep(air, out, axis)
        new = int(out.sum())
        if new == count:
            break
        count = new
    else:                                                              # not settled: keep everything
        return np.ones(M, dtype=bool)
    touch = np.zeros(shape, dtype=bool)
    touch[1:] |= out[:-1]
    touch[:-1] |= out[1:]
    touch[:, 1:] |= out[:, :-1]
    touch[:, :-1] |= out[:, 1:]
    touch[:, :, 1:] |= out[:, :, :-1]
    touch[:, :, :-1] |= out[:, :, 1:]
    result = np.zeros(M, dtype=bool)
    result[seg[touch[idx[:, 0], idx[:, 1], idx[:, 2]]]] = True
    return result
