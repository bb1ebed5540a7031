"""Extrusion with nothing under it, measured on the G-code itself.

A real cell drops filament that has nothing below it.  This module states
how much of a print is in mid-air, from the toolpath alone (whatever
slicer wrote it, with or without support), by the rule of issue
"Printable":

* the extrusions are grouped by height (within 0.001 mm); all the G-code
  given is grouped together (every arm's program of one job, in one frame);
* a point of an extrusion at height ``z`` is **supported** when some
  extrusion of *the layer below* (any program's) passes within one bead
  width of it: every extrusion at a height in ``[z - 1.75 h, z - 0.25 h]``,
  ``h`` the nominal layer height (the most common step between extruding
  heights).  That is the layer one ``h`` lower, and also a support layer a
  slicer lowers under an overhang (our z gap: 0.1 mm) or lays at heights
  of its own, up to 1.75 ``h`` thick (PrusaSlicer's support layers when
  they are not synchronized with the object's); with slabs of height ``h``
  in place of the window, such thick layers found an empty slab below and
  PrusaSlicer's support scored 15-23 % in mid-air.  The extrusions less
  than 0.25 ``h`` above the lowest lie on the bed;
* layers are reported by number ``k`` = the slab ((k - 1) h, k h] their
  height falls in (the slicer's layer number for layers of height ``h``);
* a **bridge** is allowed: a stretch of one extrusion path (consecutive
  extruding moves, end to start) that is unsupported over at most
  ``bridge_max_mm`` and has supported points at both ends counts as
  supported; the pieces of one line that coordination cut (where two
  arms' or two bands' work meets: one ends where the next begins, and no
  third path ends there) are one path for this, and so is a piece that
  ends on a vertex of another path where that path runs on in line with
  it (its other part, which turns there along a band edge): that path's
  stretch beyond the vertex spans the gap with it, counted once, in its
  own path;
* the **unsupported share** is the unsupported extruded length over the
  whole extruded length.

Points are taken every ``step_mm`` along each extruding move (each sample
stands for its stretch of the path); the distance to the layer below is
the exact distance to its extrusion segments, not to samples of them
(:class:`_Below`: a k-d tree of points on the segments settles most
samples, the distance to the segments of their nearest tree points most
of the others, GEOS's distance to all the segments the few left).
Millimetres throughout, the G-code frame.
"""
import math
from typing import Dict, Iterable, List

import numpy as np

from ambots.gcode import Segment

__all__ = ["unsupported_extrusion", "layer_ranges", "DEFAULT_BEAD_WIDTH_MM", "DEFAULT_BRIDGE_MAX_MM",
           "PARALLEL_MIN_MOVES"]

#: one bead width: the reach of the rule (the slicers' default extrusion width)
DEFAULT_BEAD_WIDTH_MM = 0.45
#: the longest unsupported stretch of a path that counts as a bridge
DEFAULT_BRIDGE_MAX_MM = 10.0
#: layers closer than this in z are one layer
_Z_TOL = 1e-3


def _paths(events):
    """Extrusion paths of one program: lists of (start, end) segments joined
    end to start, in the order printed."""
    paths, cur, last_end = [], [], None
    for ev in events:
        if type(ev) is not Segment:
            continue
        (x0, y0, z0), (x1, y1, z1) = ev.start, ev.end
        moving = x0 != x1 or y0 != y1
        if not (ev.extrude and moving):
            if moving or z0 != z1:        # a travel ends the path; a pure E move (retract/prime) does not
                if cur:
                    paths.append(cur)
                cur, last_end = [], None
            continue
        if cur and (last_end != ev.start or abs(z1 - z0) > _Z_TOL):
            paths.append(cur)
            cur = []
        cur.append((ev.start, ev.end))
        last_end = ev.end
    if cur:
        paths.append(cur)
    return paths


def extrusion_paths(events):
    """:func:`_paths` of one program as arrays ((m, 2, 3) each, mm): what
    :func:`unsupported_extrusion` measures of it (``paths``), cheap to send
    from a worker process."""
    return [np.asarray(p, dtype=float).reshape(-1, 2, 3) for p in _paths(events)]


#: the layer below is sampled at most this far apart (mm) for :class:`_Below`'s
#: k-d tree: finer settles more points by the tree, for a larger tree (on the
#: 60 mm sphere's program, one process: 0.1 mm 1.6 s, 0.2 mm 1.45 s, 0.3 mm 1.55 s)
_TREE_STEP_MM = 0.2


class _Below:
    """The extrusion of one level, ``segs`` ((m, 2, 2) xy, mm), and which
    points lie within ``reach`` (mm) of it (:meth:`near`), by the exact
    distance to the segments.

    A k-d tree of points on the segments, at most :data:`_TREE_STEP_MM`
    apart and both ends of each, settles most points: one within ``reach``
    of a tree point is within ``reach`` of that point's segment; one farther
    than ``reach`` + step / 2 from every tree point is farther than
    ``reach`` from every segment (each point of a segment lies within
    step / 2 of a tree point).  The points in between (7 % of a 60 mm
    sphere's samples) are measured to the segments of their
    :data:`_NEAREST` nearest tree points: every segment within ``reach``
    has a tree point within ``reach`` + step / 2, so that settles the point
    unless more tree points than that lie so near; then GEOS measures its
    distance to all the segments (64 of the sphere's samples, from 132,000
    before session 29).

    The tree is asked about every other point only, at first: the distance
    to the segments changes by at most the distance between two points, so
    a point next to one well within ``reach`` (or well beyond it) is
    settled by that one (:meth:`near`).

    Measured on that sphere's program (1.9 M samples, 300 layers): 1.45 s
    with every point asked and GEOS for all the points in between, against
    9.4 s for the union of the segments' buffers (a polygon with 4 segments
    a quarter circle, so a little short of the exact distance: 538.7 mm
    unsupported against 538.5 mm) and 3.7 s for GEOS's distance alone."""

    def __init__(self, segs, reach):
        from scipy.spatial import cKDTree
        self.segs, self.reach = segs, float(reach)
        a, b = segs[:, 0], segs[:, 1]
        k = np.maximum(1, np.ceil(np.hypot(*(b - a).T) / _TREE_STEP_MM)).astype(int)
        idx = np.repeat(np.arange(len(segs)), k + 1)
        j = np.arange(len(idx)) - np.repeat(np.cumsum(k + 1) - (k + 1), k + 1)
        pts = a[idx] + (b[idx] - a[idx]) * (j / k[idx])[:, None]
        self.tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
        self.seg_of = idx                 # the segment of each tree point
        self._lines = None

    def _distance(self, pts, bound):
        """(n,) distance of each point to its nearest tree point, inf beyond ``bound``."""
        return self.tree.query(pts, k=1, distance_upper_bound=bound * (1.0 + 1e-9) + 1e-9)[0]

    def near(self, pts):
        """(n,) bool: the points ``pts`` ((n, 2) xy) within ``reach`` of the segments."""
        import shapely
        n = len(pts)
        if not n:
            return np.zeros(0, dtype=bool)
        reach, half = self.reach, 0.5 * _TREE_STEP_MM
        sure = reach + half                  # a tree point farther: the segments are farther than reach
        far = sure + _TREE_STEP_MM           # ... and from a point up to a step away
        d = np.full(n, np.inf)
        d[::2] = self._distance(pts[::2], far)
        # the others, settled by a neighbour asked (|distance(p) - distance(q)| <= |p - q|):
        # within reach by its tree distance plus the gap, beyond it by the least its
        # segments can be (tree distance - step / 2, at least far - step / 2 when none is
        # that near) less the gap; each with a margin, so that no rounding decides
        odd = np.arange(1, n, 2)
        inside = np.zeros(len(odd), dtype=bool)
        outside = np.zeros(len(odd), dtype=bool)
        for j in (odd - 1, odd + 1):
            ok = j < n
            q = odd[ok]
            gap = np.hypot(*(pts[q] - pts[j[ok]]).T)
            dq = d[j[ok]]
            inside[ok] |= dq + gap <= reach - _MARGIN_MM
            outside[ok] |= np.minimum(dq, far) - half - gap > reach + _MARGIN_MM
        ask = odd[~inside & ~outside]
        d[ask] = self._distance(pts[ask], sure)
        out = np.zeros(n, dtype=bool)
        out[odd[inside]] = True
        asked = np.ones(n, dtype=bool)
        asked[odd[inside | outside]] = False
        out[asked] = d[asked] <= reach
        unsure = np.flatnonzero(asked & ~out & (d <= sure * (1.0 + 1e-9) + 1e-9))
        if len(unsure):
            # every segment within reach has a tree point within ``sure``: the segments of
            # the nearest few tree points, measured exactly, settle the point unless there
            # are more such tree points than were asked for (or a bound lands on the reach)
            dk, ik = self.tree.query(pts[unsure], k=_NEAREST, distance_upper_bound=sure * (1.0 + 1e-9) + 1e-9)
            found = np.isfinite(dk)
            seg = self.segs[self.seg_of[np.where(found, ik, 0)]]                # (u, k, 2, 2)
            a, ab, p = seg[:, :, 0], seg[:, :, 1] - seg[:, :, 0], pts[unsure][:, None, :]
            L2 = np.einsum("ukj,ukj->uk", ab, ab)
            t = np.clip(np.einsum("ukj,ukj->uk", p - a, ab) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
            dist = np.where(found, np.hypot(*np.moveaxis(a + ab * t[..., None] - p, -1, 0)), np.inf).min(axis=1)
            within = dist <= reach - _MARGIN_MM
            beyond = (dist > reach + _MARGIN_MM) & ~found[:, -1]
            out[unsure[within]] = True
            unsure = unsure[~within & ~beyond]
        if len(unsure):
            if self._lines is None:
                self._lines = shapely.multilinestrings(shapely.linestrings(self.segs))
                shapely.prepare(self._lines)
            out[unsure] = shapely.dwithin(self._lines, shapely.points(pts[unsure]), reach)
        return out


#: the tree points :meth:`_Below.near` asks for about a point it cannot settle
#: by the nearest (the segments of those within ``reach`` + step / 2 are then
#: measured; more such points: GEOS measures it)
_NEAREST = 8

#: what :meth:`_Below.near` leaves to the exact distance (GEOS) when a bound
#: lands this close to the reach (mm): far above rounding, far below a bead
_MARGIN_MM = 1e-9


def _sample(path, step_mm):
    """Sample points of one path ((m, 2, 3) array of segments, mm): (n, 2)
    xy, (n,) weights (mm of path each), (n,) the segment of each."""
    seg = path
    a, b = seg[:, 0, :2], seg[:, 1, :2]
    length = np.hypot(*(b - a).T)
    k = np.maximum(1, np.ceil(length / step_mm)).astype(int)
    idx = np.repeat(np.arange(len(seg)), k)
    # midpoints of k equal pieces of each segment
    first = np.cumsum(k) - k
    j = np.arange(len(idx)) - np.repeat(first, k)
    f = (j + 0.5) / k[idx]
    pts = a[idx] + (b[idx] - a[idx]) * f[:, None]
    return pts, (length / k)[idx], idx


def _bridged(supported, weights, path_id, bridge_max_mm):
    """``supported`` with the bridges filled in: runs of unsupported samples
    inside one path, at most ``bridge_max_mm`` long, with a supported
    sample of the same path on both sides.  Arrays of one layer's samples
    in path order (``path_id`` non-decreasing)."""
    n = len(supported)
    bad = ~supported
    if not bad.any():
        return supported.copy()
    edges = np.diff(np.concatenate([[False], bad, [False]]).astype(np.int8))
    starts = np.flatnonzero(edges == 1)           # first unsupported sample of each run
    ends = np.flatnonzero(edges == -1)            # one past its last
    # runs split where the path changes: a run belongs to one path only
    cut = np.flatnonzero(np.diff(path_id) != 0) + 1
    cut = cut[bad[cut] & bad[cut - 1]]
    starts = np.sort(np.concatenate([starts, cut]))
    ends = np.sort(np.concatenate([ends, cut]))
    cum = np.concatenate([[0.0], np.cumsum(weights)])
    length = cum[ends] - cum[starts]
    inside = (starts > 0) & (ends < n)
    inside[inside] &= (path_id[starts[inside] - 1] == path_id[starts[inside]]) & \
        (path_id[ends[inside]] == path_id[starts[inside]])
    fill = inside & (length <= bridge_max_mm + 1e-9)
    out = supported.copy()
    if fill.any():
        mark = np.zeros(n + 1, np.int64)
        np.add.at(mark, starts[fill], 1)
        np.add.at(mark, ends[fill], -1)
        out |= np.cumsum(mark[:n]) > 0
    return out


def unsupported_extrusion(programs: Iterable, bead_width_mm=DEFAULT_BEAD_WIDTH_MM,
                          bridge_max_mm=DEFAULT_BRIDGE_MAX_MM, step_mm=0.2, layer_height_mm=None, paths=None):
    """How much extrusion has nothing under it, by the rule of the module doc.

    ``programs``: iterables of G-code events (:func:`ambots.gcode.read_gcode`
    or :func:`~ambots.gcode.parse_gcode_text`), one per program, all in one
    frame (a job's programs together: a bead may rest on another arm's).
    ``layer_height_mm``: the nominal layer height ``h`` (None:
    :func:`nominal_layer_height` of the G-code).  ``paths``: the programs'
    :func:`extrusion_paths` one after the other, instead of ``programs``.

    Returns a dict: ``extruded_mm`` (extruding path length), ``unsupported_mm``,
    ``unsupported_share`` (0..1; 0 if nothing is extruded), ``bridged_mm``
    (unsupported but counted as bridges), ``layers`` (number of layers that
    extrude), ``unsupported_layers``: [{``layer`` (1 = the lowest that
    extrudes), ``z_mm`` (its top height), ``unsupported_mm``}] for every layer
    with some, and the rule's figures ``bead_width_mm``, ``bridge_max_mm``,
    ``layer_height_mm`` (the nominal ``h``).
    """
    if not bead_width_mm > 0 or not bridge_max_mm >= 0 or not step_mm > 0:
        raise ValueError("bead_width_mm and step_mm must be > 0 and bridge_max_mm >= 0")
    if paths is None:
        paths = [p for events in programs for p in _paths(events)]
    result = {"extruded_mm": 0.0, "unsupported_mm": 0.0, "unsupported_share": 0.0, "bridged_mm": 0.0,
              "layers": 0, "unsupported_layers": [], "bead_width_mm": bead_width_mm,
              "bridge_max_mm": bridge_max_mm, "layer_height_mm": None}
    if not paths:
        return result
    z = np.array([p[0][0][2] for p in paths])
    h = float(layer_height_mm) if layer_height_mm else nominal_layer_height(z)
    levels, level_of = np.unique(np.round(z / _Z_TOL).astype(np.int64), return_inverse=True)
    heights = levels * _Z_TOL
    by_level: Dict[int, List[int]] = {}
    for i, k in enumerate(level_of):
        by_level.setdefault(int(k), []).append(i)
    slab = np.ceil(heights / h - _Z_TOL / h).astype(int)          # the layer number reported
    level = lambda k: [paths[i] for i in by_level[k]]
    size = np.array([sum(len(p) for p in level(k)) for k in range(len(heights))])
    rule = (h, bead_width_mm, bridge_max_mm, step_mm)
    from ambots.parallel import fork_map, workers
    n = workers() if size.sum() >= PARALLEL_MIN_MOVES else 1
    # contiguous runs of levels of about equal numbers of moves, one a process
    cuts = np.searchsorted(np.cumsum(size), size.sum() * np.arange(1, n) / n, side="right")
    bounds = [int(c) for c in [0, *cuts, len(heights)]]
    runs = [(a, b) for a, b in zip(bounds, bounds[1:]) if b > a]
    total = unsupported = bridged = 0.0
    lost_by_slab: Dict[int, float] = {}
    for t, u, b, lost in fork_map(lambda r: _levels(level, heights, slab, r, rule), runs):
        total, unsupported, bridged = total + t, unsupported + u, bridged + b
        for layer, mm in lost.items():
            lost_by_slab[layer] = lost_by_slab.get(layer, 0.0) + mm
    first = int(slab.min())
    per_layer = [{"layer": n - first + 1, "z_mm": round(float(heights[slab == n].max()), 4),
                  "unsupported_mm": round(lost_by_slab[n], 3)} for n in sorted(lost_by_slab)]
    result.update(extruded_mm=round(total, 3), unsupported_mm=round(unsupported, 3),
                  unsupported_share=unsupported / total if total > 0 else 0.0,
                  bridged_mm=round(bridged, 3), layers=len(np.unique(slab)), unsupported_layers=per_layer,
                  layer_height_mm=h)
    return result


#: programs with at least this many extruding moves are measured by
#: :func:`ambots.parallel.workers` processes, each a run of levels (the 60 mm
#: sphere's program, 116,000 moves: 1.45 s in one process, 0.8-1.0 s in two)
PARALLEL_MIN_MOVES = 20000


def _levels(level, heights, slab, run, rule):
    """The levels ``run`` = (first, end) of :func:`unsupported_extrusion`:
    (extruded, unsupported, bridged mm, {slab: unsupported mm}).  ``level(k)``:
    the paths of level ``k``; ``rule``: (h, bead width, bridge max, step), mm.
    The levels below ``first`` that its window reaches are read first."""
    h, bead_width_mm, bridge_max_mm, step_mm = rule
    lo, hi = run
    total = unsupported = bridged = 0.0
    lost_by_slab: Dict[int, float] = {}
    arrays = lambda k: [np.asarray(p, float) for p in level(k)]        # (m, 2, 3) each, made once a level
    below = lambda paths: _Below(np.concatenate([p[:, :, :2] for p in paths]), bead_width_mm)
    carries = {j: below(arrays(j)) for j in range(lo)      # level -> its extrusion (:class:`_Below`)
               if heights[j] >= heights[lo] - 1.75 * h - _Z_TOL}
    for k in range(lo, hi):
        members = arrays(k)
        samples = [_sample(p, step_mm) for p in members]
        for j in [j for j in carries if heights[j] < heights[k] - 1.75 * h - _Z_TOL]:
            del carries[j]                  # below every later window
        under = [r for j, r in carries.items() if heights[j] <= heights[k] - 0.25 * h + _Z_TOL]
        if heights[k] < heights[0] + 0.25 * h:          # on the bed
            for _, w, _ in samples:
                total += float(w.sum())
        else:
            samples, pid = _chained(members, samples, bridge_max_mm)
            pts = np.concatenate([s for s, _, _ in samples])
            w = np.concatenate([w for _, w, _ in samples])
            own = ~np.concatenate([c for _, _, c in samples])      # context samples: counted in their own path
            hit = np.zeros(len(pts), dtype=bool)
            for r in under:
                hit[~hit] = r.near(pts[~hit])
            ok = _bridged(hit, w, pid, bridge_max_mm)
            total += float(w[own].sum())
            lost = float(w[own & ~ok].sum())
            bridged += float(w[own & ok & ~hit].sum())
            if lost > 0:
                lost_by_slab[int(slab[k])] = lost_by_slab.get(int(slab[k]), 0.0) + lost
            unsupported += lost
        if k + 1 < hi:
            carries[k] = below(members)
    return total, unsupported, bridged, lost_by_slab


def _chained(members, samples, reach_mm=0.0):
    """One layer's paths joined where two of them meet end to end and no
    third path ends there: the pieces of one line that coordination cut
    (where two arms' or two bands' work meets) are one path again for the
    bridge rule.  Where a path ends on a vertex of another path that runs
    on in line with it (the same line, cut where one band's work meets
    another's that turns along the band edge there,
    :func:`ambots.coordinate.banded._edge_links`), up to ``reach_mm`` of
    that other path's samples beyond the vertex are put next to it as
    context: they count for the bridge rule, not as this path's extrusion.
    ``samples``: (points, weights, segment of each) per path
    (:func:`_sample`).  Returns the samples in chain order as (points,
    weights, context flags) (a piece walked backwards has its samples
    reversed) and the chain id of every sample."""
    ends = {}
    key = lambda xy: (round(xy[0], 3), round(xy[1], 3))
    for i, p in enumerate(members):
        a, b = key(p[0][0]), key(p[-1][1])
        if a != b:                                  # a closed loop is a chain of its own
            ends.setdefault(a, []).append((i, 0))
            ends.setdefault(b, []).append((i, 1))
    link = {}                                       # (path, end) -> (other path, its end)
    for at in ends.values():
        if len(at) == 2 and at[0][0] != at[1][0]:
            link[at[0]], link[at[1]] = at[1], at[0]
    context = _in_line(members, samples, {at[0]: pt for pt, at in ends.items() if len(at) == 1}, reach_mm)
    seen = np.zeros(len(members), bool)
    out, pid = [], []
    none = lambda n: np.zeros(n, dtype=bool)
    # chains from a free end first, then what is left (closed rings of pieces)
    order = [i for i in range(len(members)) if (i, 0) not in link or (i, 1) not in link] + list(range(len(members)))
    for start in order:
        if seen[start]:
            continue
        chain = 0 if not pid else pid[-1][0] + 1
        # from a free head forwards, from a free tail backwards (a ring: either way)
        i, forward = start, not ((start, 0) in link and (start, 1) not in link)
        head = context.get((start, 0 if forward else 1))
        if head is not None:                       # the line before the head, ending next to it
            out.append((head[0][::-1], head[1][::-1], ~none(len(head[1]))))
            pid.append((chain, len(head[1])))
        while i is not None and not seen[i]:
            seen[i] = True
            pts, w, _ = samples[i]
            out.append((pts, w, none(len(w))) if forward else (pts[::-1], w[::-1], none(len(w))))
            pid.append((chain, len(w)))
            nxt = link.get((i, 1 if forward else 0))
            if nxt is None:
                tail = context.get((i, 1 if forward else 0))
                if tail is not None:
                    out.append((tail[0], tail[1], ~none(len(tail[1]))))
                    pid.append((chain, len(tail[1])))
                break
            i, forward = nxt[0], nxt[1] == 0
    ids = np.repeat([c for c, _ in pid], [n for _, n in pid])
    return out, ids


def _in_line(members, samples, lone, reach_mm):
    """{(path, end): (points, weights)}: for each free end of ``lone``
    ({(path, end): its point key}) that lies on an inner vertex of another
    path whose segment on one side of it runs on in line with the end's
    segment (on the far side of the vertex), that other path's samples
    from the vertex outwards, at most ``reach_mm`` of them (and one more)."""
    out = {}
    if not lone or reach_mm <= 0:
        return out
    code = lambda xy: np.round(np.asarray(xy, float) * 1000.0).astype(np.int64) @ np.array([1 << 32, 1])
    want = {}
    for (i, e), pt in lone.items():
        want.setdefault(int(code(pt)), []).append((i, e))
    sizes = np.array([len(p) for p in members])
    if not (sizes > 1).any():
        return out
    inner = np.concatenate([p[1:, 0, :2] for p in members if len(p) > 1])   # vertex v: where segment v starts
    owner = np.repeat(np.arange(len(members)), np.maximum(sizes - 1, 0))
    vertex = np.arange(len(inner)) - np.repeat(np.cumsum(np.maximum(sizes - 1, 0)) - np.maximum(sizes - 1, 0),
                                               np.maximum(sizes - 1, 0)) + 1
    codes = code(inner)
    for k in np.flatnonzero(np.isin(codes, np.array(list(want), dtype=np.int64))).tolist():
        j, v, p = int(owner[k]), int(vertex[k]), members[int(owner[k])]
        for i, e in want[int(codes[k])]:
            if i == j or (i, e) in out:
                continue
            seg = members[i][-1] if e == 1 else members[i][0]
            P = p[v][0][:2]
            u = (seg[0] if e == 1 else seg[1])[:2] - P       # along the end's segment, away from P
            nu = math.hypot(*u)
            if nu <= 0:
                continue
            pts, w, idx = samples[j]
            cut = int(np.searchsorted(idx, v))
            for far, side in ((p[v - 1][0][:2], slice(cut - 1, None, -1) if cut else slice(0, 0)),
                              (p[v][1][:2], slice(cut, None))):
                q = far - P
                if abs(u[0] * q[1] - u[1] * q[0]) <= (2e-3 + 1e-4 * math.hypot(*q)) * nu and float(u @ q) < 0:
                    sp, sw = pts[side], w[side]
                    n = int(np.searchsorted(np.cumsum(sw), reach_mm)) + 1
                    out[i, e] = (sp[:n], sw[:n])
                    break
    return out


def nominal_layer_height(z):
    """The most common step between distinct extruding heights ``z`` (mm),
    to 0.001 mm; the lowest height if there is one only."""
    zs = np.unique(np.round(np.asarray(z, float), 3))
    steps = np.round(np.diff(zs), 3)
    steps = steps[steps > _Z_TOL]
    if not len(steps):
        return float(zs[0]) if len(zs) and zs[0] > _Z_TOL else 0.2
    values, counts = np.unique(steps, return_counts=True)
    return float(values[counts == counts.max()].max())        # a tie: the larger step


def layer_ranges(layers, limit=12):
    """Layer numbers as short ranges for people: [3, 4, 5, 9] -> "3-5, 9"
    (at most ``limit`` ranges, then "... (N more)")."""
    layers = sorted(set(int(k) for k in layers))
    ranges = []
    for k in layers:
        if ranges and k == ranges[-1][1] + 1:
            ranges[-1][1] = k
        else:
            ranges.append([k, k])
    text = ["%d" % a if a == b else "%d-%d" % (a, b) for a, b in ranges]
    if len(text) > limit:
        return ", ".join(text[:limit]) + ", ... (%d more)" % (len(text) - limit)
    return ", ".join(text)
