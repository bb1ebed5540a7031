"""A stepped seam: two arms' seam moved layer by layer.

A straight seam is one vertical plane for every layer, placed so that the
two parts take their arms equally long in all.  Where the model's layers
change along the seam's normal (a ramp, a block leaning towards one arm), a
layer's two halves are then far from equal: on a 200 mm ramp rising towards
the UR10 the layers above 13 mm lie wholly on the UR10's side, and with the
layers printed in step the Kinova has nothing to do for the last third.

Here the seam keeps its normal and moves along it from layer to layer
(:func:`timed_offsets`): on each layer, the work of the layer's toolpaths
(the whole model's, :meth:`ambots.slicer.WholeModel.toolpaths`) is moved
across it at each arm's time per mm there (from the straight plan, the one
timing law) until the layer's halves take their arms equally long,
moving at most :data:`STEP_MM` from one layer to the next (the seam zone
is widened by the largest step: at a layer change an arm may be a phase
ahead of its neighbour, see :func:`ambots.coordinate.banded.banded_programs`),
and a layer narrower than the zone about its seam is not moved (it is
printed in turns whoever has it).  The job makes this plan beside the
straight one's other variants and keeps it when faster
(:func:`ambots.job._seam_plans`).
The parts are the model cut by one staircase prism (:func:`stepped_parts`);
each part keeps its straight plane (:attr:`ambots.partition.Part.planes`) and
the offset added to it on each layer
(:attr:`ambots.partition.Part.layer_offsets`).

Units: mm in the bed frame."""
import numpy as np

__all__ = ["STEP_MM", "timed_offsets", "plan_offsets", "stepped_parts", "layer_segments", "largest_step",
           "extremes", "offset_at"]

#: the most (mm) a stepped seam moves from one layer to the next; the seam
#: zone is widened by the largest step taken
STEP_MM = 0.5
#: offsets are rounded to this (mm): layers whose seam moves less than that
#: share one slab of the parts
QUANTUM_MM = 0.1


def offset_at(o, k):
    """A seam plane's offset on layer ``k``: ``o`` itself, or ``o[k]`` for a
    stepped seam's (L,) offsets (the first before them, the last beyond)."""
    return float(o) if np.ndim(o) == 0 else float(o[min(max(int(k), 0), len(o) - 1)])


def layer_segments(toolpaths):
    """Per layer of ``toolpaths`` ([:class:`ambots.slicer.LayerPaths`]),
    the extrusions as (starts (S, 2), ends (S, 2)) mm: perimeters (closed),
    infill, support and its contact layer."""
    out = []
    for lp in toolpaths:
        paths = [p for groups in lp.islands for group in groups for p in group]
        paths += list(lp.support or []) + list(lp.contact or [])
        a, b = [], []
        for p in paths:
            pts = np.asarray(p.points, dtype=float)[:, :2]
            if len(pts) < 2:
                continue
            a.append(pts[:-1])
            b.append(pts[1:])
            if p.closed:
                a.append(pts[-1:])
                b.append(pts[:1])
        out.append((np.concatenate(a), np.concatenate(b)) if a else (np.zeros((0, 2)), np.zeros((0, 2))))
    return out


def _length_above(s0, s1, lengths, d):
    """Length of the segments (projections ``s0``, ``s1`` on the normal,
    ``lengths``) with n . p >= each of ``d`` (D,) -> (D,): a segment's
    length counts in proportion to the share of its projection past d (one
    across the normal: wholly on the side of its projection)."""
    lo, hi = np.minimum(s0, s1)[None], np.maximum(s0, s1)[None]
    d = np.asarray(d, dtype=float)[:, None]
    span = hi - lo
    frac = np.where(span > 1e-9, np.clip((hi - d) / np.where(span > 1e-9, span, 1.0), 0.0, 1.0),
                    (lo >= d).astype(float))
    return (frac * lengths[None]).sum(axis=1)


def _where_above(s0, s1, lengths, target, lo, hi):
    """The d in [lo, hi] with ``target`` mm of the segments at n . p >= d
    (:func:`_length_above`, which falls as d grows), by bisection to 1e-6 mm;
    lo or hi if the target lies beyond."""
    for _ in range(60):
        if hi - lo <= 1e-6:
            break
        mid = (lo + hi) / 2.0
        if float(_length_above(s0, s1, lengths, [mid])[0]) > target:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2.0


def _limited(want, step_mm, quantum_mm):
    """``want`` (L,) rounded to ``quantum_mm`` and moving at most ``step_mm``
    from one layer to the next: limited going up, then going down."""
    out = np.round(np.asarray(want, dtype=float) / quantum_mm) * quantum_mm
    for i in range(1, len(out)):
        out[i] = np.clip(out[i], out[i - 1] - step_mm, out[i - 1] + step_mm)
    for i in range(len(out) - 2, -1, -1):
        out[i] = np.clip(out[i], out[i + 1] - step_mm, out[i + 1] + step_mm)
    return np.round(out / quantum_mm) * quantum_mm


def extremes(parts):
    """Two stepped ``parts`` (:func:`stepped_parts`) as two pairs of parts
    with straight seams, at the least and at the most the seam moves: the
    seam zone from the sampled poses is taken at both
    (:func:`ambots.coordinate.seam_zones_for`), the zone of every layer's
    seam between them."""
    from dataclasses import replace
    a, b = parts
    out = []
    for d in (float(np.min(a.layer_offsets)), float(np.max(a.layer_offsets))):
        out.append([replace(a, planes=[(n, o + d) for n, o in a.planes], layer_offsets=None),
                    replace(b, planes=[(n, o - d) for n, o in b.planes], layer_offsets=None)])
    return out


def largest_step(offsets):
    """The most (mm) ``offsets`` move from one layer to the next."""
    offsets = np.asarray(offsets, dtype=float)
    return float(np.abs(np.diff(offsets)).max()) if len(offsets) > 1 else 0.0


def stepped_parts(model, parts, offsets, z_tops, heights):
    """The two ``parts`` (:class:`ambots.partition.Part`, a straight seam)
    of ``model`` (manifold3d.Manifold) cut again with the first one's plane
    moved by ``offsets`` (L,) mm on each of the slicer's layers (``z_tops``,
    ``heights``): layers of equal offset share a slab; the lowest reaches
    down and the highest up past the model.  The first part is the model
    within the solid on its side of the stepped seam
    (:func:`_stepped_side`, one prism), the second the rest.  Returns the
    new parts, each with its :attr:`~ambots.partition.Part.layer_offsets`
    (the second's the opposite of the first's)."""
    from dataclasses import replace
    a, b = parts
    (n, off), = a.planes
    offsets = np.asarray(offsets, dtype=float)
    side = _stepped_side(model, n, off, offsets, np.asarray(z_tops, dtype=float) - np.asarray(heights, dtype=float))
    return [replace(a, manifold=model ^ side, layer_offsets=offsets.copy()),
            replace(b, manifold=model - side, layer_offsets=-offsets)]


def _stepped_side(model, normal, offset, offsets, bottoms):
    """The solid (manifold3d.Manifold) of the points ``p`` with
    ``normal . p >= offset + offsets[i]`` in the slab of each layer ``i``
    (from its bottom ``bottoms[i]`` to the next layer's, mm), reaching past
    ``model``'s box all round: a staircase in the plane of the normal and
    the vertical, extruded along the seam.  One prism, so one boolean cuts
    the model (cut slab by slab instead, a 300-layer tube whose seam moves
    on every layer took 2.3 s a part to evaluate)."""
    import manifold3d as m3
    u = np.array([float(normal[0]), float(normal[1]), 0.0])
    if abs(float(normal[2])) > 1e-9 or np.linalg.norm(u) < 1e-9:
        raise ValueError("a stepped seam needs an upright seam plane, not normal %s" % (list(normal),))
    scale = float(np.linalg.norm(u))      # n . p >= o is (n / |n|) . p >= o / |n|
    u, offset, offsets = u / scale, offset / scale, np.asarray(offsets, dtype=float) / scale
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)                    # along the seam: (u, z, v) is right-handed
    box = np.array(model.bounding_box(), dtype=float).reshape(2, 3)
    corners = np.array([[box[i][0], box[j][1], box[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    pad = 10.0 + float(np.abs(offsets).max(initial=0.0))
    across, along = corners @ u, corners @ v         # the box's corners across and along the seam
    s_far = float(across.max()) + pad
    z_lo, z_hi = float(box[0][2]) - pad, float(box[1][2]) + pad
    starts = [0] + [i for i in range(1, len(offsets)) if offsets[i] != offsets[i - 1]]
    stairs = []                           # (s, z) up the seam side of the staircase
    for g, i in enumerate(starts):
        o = float(offset + offsets[i])
        lo = z_lo if g == 0 else float(bottoms[i])
        hi = z_hi if g + 1 == len(starts) else float(bottoms[starts[g + 1]])
        stairs += [(o, lo), (o, hi)]
    # counter-clockwise in (s, z): up the far side, then down the stairs
    ring = [(s_far, z_lo), (s_far, z_hi)] + stairs[::-1]
    section = m3.CrossSection([ring], m3.FillRule.NonZero)
    length = float(along.max() - along.min()) + 2.0 * pad
    prism = m3.Manifold.extrude(section, length)         # (s, z) in x, y; the seam's direction in z
    frame = np.column_stack([u, z, v, v * (float(along.min()) - pad)])
    return prism.transform(frame.tolist())


def _layer_lengths(proj, normal_offsets):
    """Each layer's extrusion length on the first part's side of its seam
    (n . p >= offset + its offset), (L,)."""
    return np.array([float(_length_above(s0, s1, L, [o])[0]) if len(L) else 0.0
                     for (s0, s1, L), o in zip(proj, normal_offsets)])


def timed_offsets(segments, normal, offset, offsets, busy, step_mm=STEP_MM, quantum_mm=QUANTUM_MM, keep_mm=0.0):
    """The per-layer ``offsets`` (L,) of a plan moved so that each layer's
    two halves take their arms equally long: ``busy`` (2, L) s, each arm's
    time on each layer of that plan (the one timing law), the first arm's
    part on the side n . p >= offset + offsets.  A layer's work is moved
    across the seam at each arm's own time per mm of toolpath there (the
    layer's mean of both where one arm has none), by length along the
    normal; a layer narrower than ``2 keep_mm`` along the normal is not
    moved, nor its seam brought within ``keep_mm`` of its ends.  Then
    rounded to ``quantum_mm`` and moving at most ``step_mm`` from one layer
    to the next (the nearest such sequence: limited going up, then going
    down).  Returns (L,) float."""
    n = np.asarray(normal, dtype=float)[:2]
    proj = [(a @ n, b @ n, np.linalg.norm(b - a, axis=1)) for a, b in segments]
    offsets = np.asarray(offsets, dtype=float)
    busy = np.asarray(busy, dtype=float)
    la = _layer_lengths(proj, offset + offsets)
    total = np.array([float(L.sum()) for _, _, L in proj])
    lb = total - la
    want = offsets.copy()
    for i, (s0, s1, L) in enumerate(proj):
        if i >= busy.shape[1] or not total[i] > 0:
            continue
        lo, hi = float(min(s0.min(), s1.min())), float(max(s0.max(), s1.max()))
        if hi - lo < 2 * keep_mm:
            continue
        ta, tb = busy[0, i], busy[1, i]
        rate = (ta + tb) / total[i]
        ra = ta / la[i] if la[i] > 1e-6 and ta > 0 else rate
        rb = tb / lb[i] if lb[i] > 1e-6 and tb > 0 else rate
        target = float(np.clip(la[i] - (ta - tb) / (ra + rb), 0.0, total[i]))
        d = _where_above(s0, s1, L, target, lo + keep_mm, hi - keep_mm)
        got = float(_length_above(s0, s1, L, [d])[0]) - la[i]
        if abs(got) > FLAT_SHARE * total[i]:
            want[i] = d - offset
        # else the work cannot change hands there (a gap between islands, the balance
        # beyond reach): the seam stays, rather than creep across the gap a step a layer
    return _limited(want, step_mm, quantum_mm)


#: a layer whose work on each side of the seam would change by less than this
#: share of its length keeps its seam where it is (:func:`timed_offsets`): two
#: towers 200 mm apart, their seam crept 78.6 mm across the gap between them
#: a step a layer, towards the slower arm's tower, without moving any work,
#: and brought the tower within the zone (5,672 s against 4,942 s straight)
FLAT_SHARE = 1e-3


#: a stepped seam is tried only where it moves at least this far (mm) on some layer
STEPPED_MIN_MM = 1.0


def plan_offsets(parts, sliced, layer_busy, toolpaths, keep_mm):
    """The per-layer offsets (:func:`timed_offsets`) for a plan of two
    ``parts`` with a straight seam: ``sliced`` {arm name: its G-code, the
    whole model's toolpaths clipped}, ``layer_busy`` {arm name: (L',) s it
    moves on each layer of its program, :func:`ambots.estimate.makespan`},
    ``toolpaths`` the whole model's (:meth:`ambots.slicer.WholeModel.toolpaths`).
    A program's layer j is its G-code's j-th layer, matched to the whole
    model's by its ``;Z:`` (a part may lack layers).  None when the seam
    would move less than :data:`STEPPED_MIN_MM` on every layer."""
    import re
    if len(parts) != 2 or any(len(p.planes) != 1 for p in parts):
        return None
    index = {round(float(lp.z), 3): i for i, lp in enumerate(toolpaths)}
    busy = np.zeros((2, len(toolpaths)))
    for row, p in enumerate(parts):
        per = np.asarray(layer_busy[p.arm.name], dtype=float)
        zs = re.findall(r"^;Z:(-?[0-9.]+)$", str(sliced[p.arm.name]), flags=re.M)
        for j, z in enumerate(zs[:len(per)]):
            i = index.get(round(float(z), 3))
            if i is not None:
                busy[row, i] += per[j]
    (n, off), = parts[0].planes
    offsets = timed_offsets(layer_segments(toolpaths), n, off, np.zeros(len(toolpaths)), busy, keep_mm=keep_mm)
    return offsets if np.abs(offsets).max() >= STEPPED_MIN_MM else None
