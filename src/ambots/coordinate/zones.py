"""Seams between the arms' parts: the plane between every two parts, how
far apart two nozzles across it must stay (the seam zone, from the arms'
geometry), which arms are *adjacent* (their work comes within the zone of
each other), and whether the adjacent arms can be given two colours.

Units: mm in the bed frame."""
import math

import numpy as np

__all__ = ["seam_planes", "LayerPlanes", "planes_at", "adjacent_arms", "seam_zone_for", "seam_zones_for",
           "distance_to_planes", "two_colours"]


def distance_to_planes(points, planes):
    """(N, 3) points, [(n, off)] -> (N, P) signed distances (inside >= 0)."""
    if not planes:
        return np.zeros((len(points), 0))
    normals = np.array([n for n, _ in planes])
    offs = np.array([o for _, o in planes])
    return points @ normals.T - offs


class LayerPlanes(dict):
    """{arm: [(n, off)]}, each arm's planes against its neighbours, with a
    stepped seam's offsets per layer (:mod:`ambots.seam_steps`): ``shifts``
    {arm: (L,) mm added to each of the arm's offsets on each layer}.  As a
    dict it gives the straight planes; :func:`planes_at` a layer's."""

    def __init__(self, planes, shifts):
        super().__init__(planes)
        self.shifts = {a: np.asarray(s, dtype=float) for a, s in shifts.items() if s is not None}

    def at(self, arm, layer):
        s = self.shifts.get(arm)
        if s is None or not len(s):
            return self[arm]
        from ambots.seam_steps import offset_at
        d = offset_at(s, layer)
        return [(n, off + d) for n, off in self[arm]]


def planes_at(planes, arm, layer):
    """``arm``'s planes on ``layer``: ``planes[arm]``, or a
    :class:`LayerPlanes`' planes of that layer."""
    return planes.at(arm, layer) if isinstance(planes, LayerPlanes) else planes[arm]


def seam_planes(parts):
    """The plane between every two parts, from each side: {(a, b): (n, o)}
    with a's signed distance ``n . p - o`` (mm, >= 0 on a's side), for arm
    names a != b.  ``parts[i].planes[j]`` bounds part i against the arm
    ``parts[i].neighbours[j]``; with an interlocking seam the two parts'
    planes are 2 d apart (each reaches d past the seam on its layers) and
    the plane returned is the one midway, the true seam.  Planes against arms without a part here are left out."""
    own = {}
    names = [p.arm.name for p in parts]
    for p in parts:
        others = list(getattr(p, "neighbours", None) or [])
        if len(others) != len(p.planes):      # a Part made without neighbours: the other arms in order
            others = [n for n in names if n != p.arm.name]
        for other, (n, off) in zip(others, p.planes):
            own[p.arm.name, other] = (np.asarray(n, dtype=float), float(off))
    out = {}
    for (a, b), (n, off) in own.items():
        if b not in names or a == b:
            continue
        o = (off - own[b, a][1]) / 2.0 if (b, a) in own else off
        out[a, b] = (n, o)
    return out


def adjacent_arms(arms, read, planes, zones):
    """{arm: set of arms} whose extrusions come within the pair's zone of each
    other across the plane between them (sum of the two distances), in any
    layer.  ``read``: {arm name: (removed lines, {layer: [Segment]})}, the
    sliced G-code as :func:`ambots.coordinate.steps.read_sliced` gives it."""
    names = [a.name for a in arms]
    pts = {}
    for n in names:
        segs = [s for layer in read[n][1].values() for s in layer if s.extrude and s.start != s.end]
        pts[n] = np.array([s.start for s in segs] + [s.end for s in segs], dtype=float).reshape(-1, 3)
    adjacent = {n: set() for n in names}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if (a, b) not in planes or (b, a) not in planes or not len(pts[a]) or not len(pts[b]):
                continue
            nrm, o = planes[a, b]
            da = float(np.min(pts[a] @ nrm - o))
            db = float(np.min(o - pts[b] @ nrm))
            if da + db < zones[a, b]:
                adjacent[a].add(b)
                adjacent[b].add(a)
    return adjacent


_ZONES = {}
#: the zones of a job's parts, by the parts' planes and boxes (a few jobs' worth)
_PART_ZONES = {}


def seam_zone_for(cell, arms):
    """Seam zone (mm) of these arms of the cell: the largest of
    :func:`seam_zones_for` (cached)."""
    if len(arms) < 2:
        return 0.0
    return max(seam_zones_for(cell, arms).values())


def seam_zones_for(cell, arms, parts=None):
    """Seam zone (mm) of every pair of these arms, from their geometry
    (:func:`ambots.collision.seam_zones_mm`): {(a, b): mm}, both orders.
    From the poses on the arms' shares of the whole bed (cached); with
    ``parts`` (a job's), the larger of that and the zone from the poses on
    those parts (the parts' planes can differ from the shares', and two arms
    whose shares are far apart can get parts that meet), or the zone the
    sampled poses on the parts keep clear if smaller
    (``seam_zones_mm(..., clearance=)``: for arms that do not face each
    other along their seam, a beam's or four in the corners of a bed)."""
    from ambots.collision import seam_zones_mm
    if len(arms) < 2:
        return {}
    key = (cell.path if hasattr(cell, "path") else cell.name, tuple(a.name for a in arms))
    if key not in _ZONES:
        _ZONES[key] = {k: float(v) for k, v in seam_zones_mm(cell, arms).items()}
    zones = dict(_ZONES[key])
    if parts is not None:
        # the same parts again (a job's plans with other chunk bands): the same zones
        part_key = key + tuple((p.arm.name, tuple(p.neighbours), tuple(p.manifold.bounding_box()),
                                tuple((tuple(float(x) for x in n), float(o)) for n, o in p.planes)) for p in parts)
        if part_key not in _PART_ZONES:
            tight = {}
            _PART_ZONES[part_key] = ({k: float(v) for k, v in
                                      seam_zones_mm(cell, arms, parts=parts, clearance=tight).items()}, tight)
            while len(_PART_ZONES) > 16:
                _PART_ZONES.pop(next(iter(_PART_ZONES)))
        projected, tight = _PART_ZONES[part_key]
        for k, v in projected.items():
            zones[k] = max(zones.get(k, 0.0), v)
        for k, v in tight.items():          # the poses' own clearance, if smaller
            zones[k] = min(zones[k], float(v))
    # rounded up to 0.01 mm: the last bits of the sums vary with how BLAS
    # threads split them, and band edges cut segments: the same job must get
    # the very same programs every time
    return {k: math.ceil(v * 100.0 - 1e-6) / 100.0 for k, v in zones.items()}


def two_colours(names, adjacent):
    """{arm: 0 or 1} with adjacent arms of different colours, or None if
    the adjacency graph has an odd cycle (three arms around a point)."""
    colour = {}
    for root in names:
        if root in colour:
            continue
        colour[root] = 0
        todo = [root]
        while todo:
            a = todo.pop()
            for b in sorted(adjacent[a], key=names.index):
                if b not in colour:
                    colour[b] = 1 - colour[a]
                    todo.append(b)
                elif colour[b] == colour[a]:
                    return None
    return colour
