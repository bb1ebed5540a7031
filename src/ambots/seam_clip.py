"""An arm's part of the whole model's toolpaths: the paths clipped to the
part's prism.

With a straight seam every part is the model cut by vertical planes
(:attr:`ambots.partition.Part.planes`), so its layer is the whole model's
layer cut by half-planes.  Slicing each part on its own puts perimeters on
both faces of every seam: walls inside the model that a single arm never
prints (on the 240 mm demo block, each arm's half took about 8 % more than
half of its time for the whole block; the walls were part of that).
Clipping the whole model's toolpaths instead gives every arm the lines a
single arm would print there, cut where they cross the seam: the outer
perimeter runs on across the seam, infill lines meet end to end, and the
parts' paths together are the whole model's.

Each seam is one plane for both of its arms (:func:`prisms`): the part
whose arm name sorts first keeps n . p - offset >= 0, its neighbour the
rest (< 0) of the same numbers, and a crossing point is computed from the
same two ends by both, so no piece of path is printed twice or lost.

Units: mm in the bed frame (the G-code's)."""
import math

import numpy as np

__all__ = ["prisms", "at_layer", "clip_layer", "clip_paths"]


def prisms(parts):
    """{arm name: [(n (2,), offset, side)]} for the parts of a straight seam
    (:class:`ambots.partition.Part`): the half-planes of each part's prism,
    ``side`` +1 keeping n . p - offset >= 0, -1 keeping < 0 (the
    neighbour's plane, whose arm name sorts first); None if a plane is not
    vertical or a neighbour's plane is missing.  A stepped seam's offset is
    per layer, (L,) (:func:`at_layer`)."""
    by_name = {p.arm.name: p for p in parts}
    out = {}
    for p in parts:
        planes = []
        for (n, off), other in zip(p.planes, p.neighbours):
            if abs(float(n[2])) > 1e-12:
                return None
            if p.arm.name < other or other not in by_name:
                planes.append((np.array([float(n[0]), float(n[1])]), _offsets(off, p), 1))
                continue
            theirs = by_name[other]
            if p.arm.name not in theirs.neighbours:
                return None
            m, o = theirs.planes[theirs.neighbours.index(p.arm.name)]
            planes.append((np.array([float(m[0]), float(m[1])]), _offsets(o, theirs), -1))
        out[p.arm.name] = planes
    return out


def _offsets(off, part):
    """A plane's offset: a float, or per layer (L,) for a stepped seam's part
    (:attr:`ambots.partition.Part.layer_offsets`)."""
    steps = getattr(part, "layer_offsets", None)
    return float(off) if steps is None else float(off) + np.asarray(steps, dtype=float)


def at_layer(planes, index):
    """A prism's ``planes`` (:func:`prisms`) on layer ``index``: a stepped
    seam's per-layer offsets taken there (the last beyond them)."""
    from ambots.seam_steps import offset_at
    return [(n, offset_at(off, index), side) for n, off, side in planes]


def clip_layer(layer, planes, link_max=None):
    """A :class:`ambots.slicer.LayerPaths` clipped to the prism ``planes``
    (one part's of :func:`prisms`), or None if nothing of it is left.
    ``link_max``: {infill feature: mm}; infill lines of that feature cut
    by a plane whose cut ends are nearer than this on the plane are joined
    there, unless the link would cross one of the island's perimeter loops
    (the zig-zag the slicer makes at an outline,
    :func:`ambots.slicer.chain_lanes`)."""
    from ambots.slicer import loop_segments
    link_max = link_max or {}
    has_support = layer.support is not None
    contact = clip_paths(layer.contact or [], planes) if has_support else []
    support = clip_paths(layer.support, planes) if has_support else []
    islands = []
    for groups in layer.islands:
        kept = []
        walls = [seg for group in groups for seg in loop_segments(group)]
        walls = np.concatenate(walls) if walls else None
        for group in groups:
            features = {p.feature for p in group}
            link = link_max.get(features.pop(), 0.0) if len(features) == 1 else 0.0
            group = clip_paths(group, planes, link, walls)
            if group:
                kept.append(group)
        if kept:
            islands.append(kept)
    if not (contact or support or islands):
        return None
    if not (contact or support):
        return layer._replace(contact=None, support=None, islands=islands)
    return layer._replace(contact=contact, support=support, islands=islands)


def clip_paths(paths, planes, link_max=0.0, walls=None):
    """``paths`` (:class:`ambots.slicer.Path`) cut to the prism: a path
    wholly inside is kept as it is (a loop stays a loop), one wholly
    outside is dropped, one that crosses a plane becomes the open pieces
    inside, in its own direction.  Two pieces in a row whose facing ends
    were both cut by the same plane, less than ``link_max`` (mm) apart,
    are joined by a line along the plane, unless that line crosses one of
    ``walls`` ((p, 2, 2) segments, :func:`ambots.slicer.crossing`)."""
    for n, off, side in planes:
        out = []
        for path in paths:
            s = path.points @ n - off
            inside = s >= 0.0 if side > 0 else s < 0.0
            if inside.all():
                out.append(path)
            elif inside.any():
                out += [path._replace(points=q, closed=False) for q in _pieces(path, s, inside)]
        paths = _joined(out, n, off, link_max, walls) if link_max > 0 and len(out) > 1 else out
    return paths


def _joined(paths, n, off, link_max, walls=None):
    """Consecutive open paths joined where the first ends and the next
    starts (or ends: it is then reversed) on the plane (n, off), less than
    ``link_max`` apart and not across one of ``walls``."""
    from ambots.slicer import crossing, wall_boxes
    boxes = None if walls is None else wall_boxes(walls)

    def on(p):
        return abs(float(p @ n) - off) <= 1e-7

    def clear(a, b):
        return walls is None or not crossing(a[None], b[None], walls, boxes)[0]

    out = [paths[0]]
    for path in paths[1:]:
        last = out[-1]
        if not last.closed and not path.closed and on(last.points[-1]):
            end = last.points[-1]
            for q in (path.points, path.points[::-1]):
                if on(q[0]) and math.hypot(*(q[0] - end)) <= link_max and clear(end, q[0]):
                    out[-1] = last._replace(points=np.concatenate([last.points, q]))
                    break
            else:
                out.append(path)
            continue
        out.append(path)
    return out


def _pieces(path, s, inside):
    """The runs of ``path`` inside (``inside`` per point, ``s`` the signed
    distances to the plane): (k, 2) arrays, each longer than the writer's
    resolution."""
    P = path.points
    if path.closed:                  # start at a point outside: no run wraps round the end
        k = int(np.argmin(inside))
        P, s, inside = (np.concatenate([P[k:], P[:k], P[k:k + 1]]), np.concatenate([s[k:], s[:k], s[k:k + 1]]),
                        np.concatenate([inside[k:], inside[:k], inside[k:k + 1]]))
    # run i: the points inside from firsts[i] to lasts[i], with the point
    # where the path entered before them and where it left after them
    step = np.diff(inside.astype(np.int8))
    enter, leave = np.flatnonzero(step > 0), np.flatnonzero(step < 0)
    k = np.concatenate([enter, leave])
    X = P[k] + (P[k + 1] - P[k]) * (s[k] / (s[k] - s[k + 1]))[:, None]
    Xin, Xout = X[:len(enter)], X[len(enter):]
    firsts = np.concatenate([[0], enter + 1]) if inside[0] else enter + 1
    lasts = np.concatenate([leave, [len(P) - 1]]) if inside[-1] else leave
    lead = 1 if inside[0] else 0
    pieces = []
    for i, (a, b) in enumerate(zip(firsts.tolist(), lasts.tolist())):
        parts = [P[a:b + 1]]
        if i >= lead:
            parts.insert(0, Xin[i - lead:i - lead + 1])
        if i < len(leave):
            parts.append(Xout[i:i + 1])
        q = np.concatenate(parts) if len(parts) > 1 else parts[0].copy()
        if len(q) > 1 and np.hypot(*(q[1:] - q[:-1]).T).sum() > 5e-4:
            pieces.append(q)
    return pieces
