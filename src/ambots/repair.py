"""Mesh repair: close the holes of an open mesh when the defect is small.

CAD exports and scans often miss a few triangles or leave a face open.  The
holes are closed by MeshFix (``pymeshfix``, the low-level ``PyTMesh``
binding: no pyvista), which fills every boundary loop with a triangulation
of the loop's own corners (no refinement: no new vertices).  trimesh's own ``fill_holes`` closes
only holes of 3 or 4 edges; manifold3d needs a closed mesh to start with.
Holes that touch each other at a corner (MeshFix would fill them as one,
with edges three triangles share) are traced loop by loop and each filled
alone first (:func:`hole_loops`, :func:`fill_loop`).  A surface that crosses
itself is found by :func:`ambots.selfcross.crossing_pairs` and repaired
when the defect is small (:func:`ambots.selfcross.repair_crossings`: its own rule).

**The rule** ("small against the model"): a repair is kept when both

* the fill adds at most :data:`MAX_FILL_AREA_SHARE` of the repaired surface
  area (the file must hold most of the surface), and
* it changes the volume by at most :data:`MAX_VOLUME_CHANGE`.

"Volume before" of an open mesh is the volume of the points whose
generalized winding number with respect to it is >= 0.5 (Jacobson et al.
2013, "Robust inside-outside segmentation using generalized winding
numbers"), judged hole by hole (the other holes taken as closed: the
deficits of several holes add up, see :func:`winding_volume`).  A closed
model with a few triangles missing, a box with its bottom left open or a
cup keep their volume (0 % change); a large hole in a curved surface,
whose flat fill departs from the surface the winding number implies (a
bowl, a sphere with an octant cut away: +4 to +6 %), does not, and is refused with the figures; so is a band (a short tube
open at both ends), whose fill would be two thirds of its surface.

The winding number is linear in the triangles, and the repaired mesh is the
open mesh plus the patch (minus any triangle MeshFix removed), so
``w_open(p) = w_repaired(p) - w_patch(p)``; ``w_patch`` can reach 0.5
only near the patch, so only the patch's bounding box is sampled
(:data:`WINDING_SAMPLES` stratified points shared by the holes), which
keeps the measure cheap on meshes of millions of triangles.

Units: mm, mm^2, mm^3 (the mesh's frame).
"""
from dataclasses import asdict, dataclass, field

import numpy as np
import trimesh

from ambots.errors import MeshError

#: most a repair may change the volume, as a share of the volume before
MAX_VOLUME_CHANGE = 0.03
#: most of the repaired surface area the fill may make up
MAX_FILL_AREA_SHARE = 0.5
#: sample points of the winding-number volume estimate (in the patch's box)
WINDING_SAMPLES = 24 ** 3


@dataclass
class RepairReport:
    """What the repair of one model did (job.json's ``"repair"``).

    Counts are of triangles and edges; areas in mm^2, volumes in mm^3;
    ``volume_change`` is a share (0.01 = 1 %) of ``volume_before_mm3``.
    ``notes``: every repair made on load, in words (filled by the job);
    ``path``: the repaired mesh's file in the job folder, once written."""
    holes_closed: int = 0
    faces_before: int = 0
    faces_after: int = 0
    faces_added: int = 0
    faces_removed: int = 0
    open_edges_before: int = 0
    open_edges_after: int = 0
    fill_area_mm2: float = 0.0
    fill_area_share: float = 0.0
    volume_before_mm3: float = None
    volume_after_mm3: float = None
    volume_change: float = None
    shells_merged: int = 0
    crossing_pairs: int = 0
    crossing_area_mm2: float = 0.0
    crossing_area_share: float = 0.0
    method: str = ""
    rule: str = ""
    notes: list = field(default_factory=list)
    path: str = None

    @property
    def changed(self):
        """Whether the geometry changed (holes closed or shells merged)."""
        return bool(self.holes_closed or self.shells_merged or self.faces_added or self.faces_removed)

    def as_dict(self):
        out = asdict(self)
        for k in ("fill_area_mm2", "crossing_area_mm2", "volume_before_mm3", "volume_after_mm3"):
            if out[k] is not None:
                out[k] = round(float(out[k]), 3)
        for k in ("fill_area_share", "crossing_area_share", "volume_change"):
            if out[k] is not None:
                out[k] = round(float(out[k]), 5)
        return out


def rule_text():
    """The repair rule in words (reports and docs)."""
    return ("fill <= %g %% of the surface area and volume change <= %g %% (volume before: winding "
            "number >= 0.5)" % (100 * MAX_FILL_AREA_SHARE, 100 * MAX_VOLUME_CHANGE))


def repair_lines(report):
    """Lines for people about a repair (``report``: :meth:`RepairReport.as_dict`);
    none when nothing was repaired."""
    if not report or not (report.get("holes_closed") or report.get("shells_merged")
                          or report.get("faces_added") or report.get("faces_removed")):
        return []
    parts = []
    if report.get("holes_closed"):
        parts.append("%d hole%s closed (%+d triangles, %.1f mm2 = %.1f %% of the surface), open edges %d -> %d"
                     % (report["holes_closed"], "" if report["holes_closed"] == 1 else "s",
                        report["faces_added"] - report["faces_removed"], report["fill_area_mm2"],
                        100 * report["fill_area_share"], report["open_edges_before"],
                        report["open_edges_after"]))
    if report.get("crossing_pairs"):
        parts.append("surface crossed itself (%d pair%s of triangles): %d triangles removed (%.1f mm2 = %.2f %% "
                     "of the surface)" % (report["crossing_pairs"], "" if report["crossing_pairs"] == 1 else "s",
                                          report["faces_removed"], report["crossing_area_mm2"],
                                          100 * report["crossing_area_share"]))
    if report.get("shells_merged"):
        parts.append("%d overlapping shells merged" % report["shells_merged"])
    line = "repaired: " + "; ".join(parts)
    if report.get("volume_before_mm3") is not None and (report.get("holes_closed")
                                                         or report.get("crossing_pairs")):
        line += "; volume %.1f -> %.1f mm3 (%+.2f %%)" % (
            report["volume_before_mm3"], report["volume_after_mm3"], 100 * report["volume_change"])
    if report.get("path"):
        line += "; repaired mesh: %s" % report["path"]
    return [line]


# ------------------------------------------------------------------ holes

def close_holes(mesh, name, report):
    """Close the holes of ``mesh`` (welded, winding consistent); return the
    closed mesh (a new Trimesh; ``mesh`` is not changed) and fill ``report``.

    Raises MeshError naming ``name`` and the figures when the repair breaks
    the rule (:data:`MAX_FILL_AREA_SHARE`, :data:`MAX_VOLUME_CHANGE`)."""
    report.method = "pymeshfix (MeshFix) fill_small_boundaries"
    report.rule = rule_text()
    report.open_edges_before = open_edges(mesh)
    try:
        closed, added, removed, report.holes_closed, pinched_loops = _fill(mesh)
    except Exception as exc:  # noqa: BLE001 -- boundary to a third-party C++ library
        report.notes.append("MeshFix failed (%s: %s); holes left open" % (type(exc).__name__, exc))
        report.open_edges_after = report.open_edges_before
        return mesh.copy()               # validate_mesh refuses it, with the open-edge count
    report.open_edges_after = open_edges(closed)
    if pinched_loops:
        report.method += "; holes that touch at a corner: each loop alone, minimal-area triangulation"
        report.notes.append("%d hole%s touching another at a corner filled one loop at a time"
                            % (pinched_loops, "" if pinched_loops == 1 else "s"))
    pinched = nonmanifold_edges(closed)
    if pinched:                          # holes that touch each other: MeshFix's fill is not a surface
        report.notes.append("MeshFix's fill left %d edges shared by more than two triangles" % pinched)
        raise MeshError("%s: not a closed volume: %d open edges; closing them gives %d edges shared by more "
                        "than two triangles (holes that touch each other at a corner or an edge, and a loop "
                        "of more than %d corners or with no triangulation of its own corners): not repaired"
                        % (name, report.open_edges_before, pinched, MAX_LOOP_CORNERS))
    with np.errstate(divide="ignore", invalid="ignore"):
        if report.open_edges_after == 0 and closed.volume < 0:
            closed.invert()                  # and the patch with it: it is part of the outward mesh
            added = trimesh.Trimesh(added.vertices, added.faces[:, ::-1], process=False)
            removed = trimesh.Trimesh(removed.vertices, removed.faces[:, ::-1], process=False)
    report.faces_added, report.faces_removed = len(added.faces), len(removed.faces)
    report.fill_area_mm2 = float(added.area)
    report.fill_area_share = float(added.area / closed.area) if closed.area > 0 else 1.0
    if report.open_edges_after:
        return closed                    # validate_mesh refuses it, with the open-edge count
    with np.errstate(divide="ignore", invalid="ignore"):
        report.volume_after_mm3 = float(closed.volume)
        report.volume_before_mm3 = winding_volume(closed, added, removed)
    before, after = report.volume_before_mm3, report.volume_after_mm3
    report.volume_change = (after - before) / before if before > 0 else float("inf")
    why = []
    if abs(report.volume_change) > MAX_VOLUME_CHANGE:
        why.append("repair would change the volume from %.1f to %.1f mm^3 (%s), more than %g %%" % (
            before, after, "%+.1f %%" % (100 * report.volume_change) if before > 0
            else "the open surface encloses no volume", 100 * MAX_VOLUME_CHANGE))
    if report.fill_area_share > MAX_FILL_AREA_SHARE:
        why.append("the fill would be %.1f mm^2, %.1f %% of the surface, more than %g %%" % (
            report.fill_area_mm2, 100 * report.fill_area_share, 100 * MAX_FILL_AREA_SHARE))
    if why:
        raise MeshError("%s: not a closed volume: %d open edges in %d hole%s, too large to repair: %s"
                        % (name, report.open_edges_before, report.holes_closed,
                           "" if report.holes_closed == 1 else "s", "; ".join(why)))
    return closed


#: meshes with more triangles give MeshFix only the triangles within two
#: rings of the holes (MeshFix builds its own mesh: 18 s for 327,680 triangles)
LOCAL_FILL_TRIANGLES = 20_000


def _fill(mesh):
    """Fill every hole of ``mesh`` with MeshFix; returns (closed mesh,
    added triangles, removed triangles, holes filled), the triangles as
    Trimeshes keeping their orientation, and how many of those holes
    touch another at a corner (filled first, each loop alone:
    :func:`_fill_pinched`).

    Large meshes: MeshFix gets the triangles within two rings of the holes;
    the patches it also puts on that region's own outer border (no hole of
    the model) are dropped, the others added to the whole mesh."""
    from pymeshfix import PyTMesh
    mesh, pre, n_pre = _fill_pinched(mesh)    # holes that touch at a corner: each loop alone
    if n_pre and not open_edges(mesh):
        return _assemble(mesh, np.ones(len(mesh.faces) - len(pre), dtype=bool), pre, np.zeros((0, 3), int),
                         n_pre) + (n_pre,)
    border = np.unique(mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)])
    region = np.arange(len(mesh.faces))
    if len(mesh.faces) > LOCAL_FILL_TRIANGLES:
        ring = np.unique(mesh.faces[np.isin(mesh.faces, border).any(axis=1)])
        region = np.flatnonzero(np.isin(mesh.faces, ring).any(axis=1))
    sub = trimesh.Trimesh(mesh.vertices, mesh.faces[region], process=False)
    fixer = PyTMesh(False)
    fixer.load_array(np.ascontiguousarray(sub.vertices, dtype=np.float64),
                     np.ascontiguousarray(sub.faces, dtype=np.int32))
    n_filled = int(fixer.fill_small_boundaries(nbe=0, refine=False))
    out = trimesh.Trimesh(*fixer.return_arrays(), process=False)
    added, removed = _patch(sub, out)
    triangles = out.vertices[out.faces[added]]
    if len(region) < len(mesh.faces) and len(added):
        # the region's outer border: its open edges that are not the model's
        sub_border = np.unique(sub.edges_sorted[trimesh.grouping.group_rows(sub.edges_sorted, require_count=1)])
        outer = {tuple(p) for p in np.round(mesh.vertices[np.setdiff1d(sub_border, border)], 9).tolist()}
        labels = _patch_labels(triangles)
        on_outer = np.array([any(tuple(p) in outer for p in t) for t in np.round(triangles, 9).tolist()])
        drop = np.isin(labels, labels[on_outer])
        n_filled -= len(np.unique(labels[on_outer]))
        triangles, added = triangles[~drop], added[~drop]
    keep = np.ones(len(mesh.faces), dtype=bool)
    keep[region[removed]] = False
    n_open = len(mesh.faces) - len(pre)          # the triangles of the open mesh come first
    gone = region[removed]
    keep, gone = keep[:n_open], mesh.faces[gone[gone < n_open]]
    pre = pre[~np.isin(np.arange(len(pre)) + n_open, region[removed])]
    return _assemble(mesh, keep, np.concatenate([pre, triangles]), gone, n_pre + n_filled) + (n_pre,)


def _assemble(mesh, keep, triangles, gone, n_filled):
    """(closed mesh, added, removed, holes filled) of :func:`_fill`: the
    first ``len(keep)`` triangles of ``mesh`` (the open mesh) where
    ``keep``, plus ``triangles`` ((k, 3, 3)); ``gone``: the vertex indices
    of the open mesh's triangles MeshFix removed."""
    closed = trimesh.Trimesh(np.concatenate([mesh.vertices, triangles.reshape(-1, 3)]),
                             np.concatenate([mesh.faces[:len(keep)][keep],
                                             len(mesh.vertices) + np.arange(3 * len(triangles)).reshape(-1, 3)]),
                             process=False)
    closed.merge_vertices()
    closed.remove_unreferenced_vertices()
    return (closed, trimesh.Trimesh(triangles.reshape(-1, 3), np.arange(3 * len(triangles)).reshape(-1, 3),
                                    process=False),
            trimesh.Trimesh(mesh.vertices, np.asarray(gone).reshape(-1, 3), process=False), n_filled)


# ------------------------------------------------- holes touching at a corner

#: most corners of a hole loop filled by the minimal-area triangulation
#: (holes that touch another at a corner; O(n^3): docs/pipeline.md, "Mesh repair")
MAX_LOOP_CORNERS = 150


def hole_loops(mesh):
    """The holes of ``mesh`` (winding consistent) as loops of vertex
    indices, each a simple cycle of open edges running against the
    triangles beside it (the way a fill triangle must run them).

    Where holes touch at a vertex (a pinch: several open edges leave it),
    an edge arriving there is paired with the edge that leaves across the
    same gap between two fans of triangles: not the edge of its own fan
    (found by walking the fan) and, with more than two fans, the first
    one clockwise (seen from outside) about the vertex's normal.  Returns
    (loops, pinch vertices)."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    # open edges: one integer per undirected edge, those met once (2x faster than group_rows)
    key = (np.minimum(directed[:, 0], directed[:, 1]) * (int(faces.max(initial=0)) + 1)
           + np.maximum(directed[:, 0], directed[:, 1]))
    order = np.argsort(key, kind="stable")
    step = key[order][1:] != key[order][:-1]
    once = order[np.concatenate([[True], step]) & np.concatenate([step, [True]])]
    hole = directed[np.sort(once)][:, ::-1]      # open edges, run against their triangle
    if not len(hole):
        return [], np.zeros(0, dtype=np.int64)
    leaving = {}
    for k, a in enumerate(hole[:, 0].tolist()):
        leaving.setdefault(a, []).append(k)
    pinch = np.array(sorted(v for v, ks in leaving.items() if len(ks) > 1), dtype=np.int64)
    following = {k: leaving[v][0] for k, v in enumerate(hole[:, 1].tolist()) if len(leaving.get(v, ())) == 1}
    if len(pinch):
        near = np.flatnonzero(np.isin(faces, pinch).any(axis=1))      # only the fans of the pinches
        face_of = {(a, b): f for f, row in zip(near.tolist(), faces[near].tolist())
                   for a, b in ((row[0], row[1]), (row[1], row[2]), (row[2], row[0]))}
        for v in pinch.tolist():
            used = set()
            for k in np.flatnonzero(hole[:, 1] == v).tolist():
                u = int(hole[k, 0])
                own = _own_fan_edge(faces, face_of, v, u)
                candidates = [e for e in leaving[v] if e not in used and hole[e, 1] != own] or \
                    [e for e in leaving[v] if e not in used]
                e = min(candidates, key=lambda e: _clockwise(mesh, v, u, int(hole[e, 1])))
                following[k] = e
                used.add(e)
    loops, seen = [], np.zeros(len(hole), dtype=bool)
    for start in range(len(hole)):
        if seen[start]:
            continue
        loop, k = [], start
        while k is not None and not seen[k]:
            seen[k] = True
            loop.append(int(hole[k, 0]))
            k = following.get(k)
        loops.append(loop)
    return loops, pinch


def _own_fan_edge(faces, face_of, v, u):
    """The far vertex of the open edge that bounds, at ``v``, the fan of
    triangles holding the directed edge v->u: walked across the fan."""
    a = u
    for _ in range(len(face_of)):
        f = faces[face_of[(v, a)]].tolist()
        i = f.index(v)
        w = f[(i + 2) % 3]                       # the triangle (v, a, w): its other edge at v is w->v
        if (v, w) not in face_of:
            return w
        a = w
    return None


def _clockwise(mesh, v, u, x):
    """Clockwise angle (rad, seen from outside) from direction v->u to v->x
    about the vertex normal of ``v``."""
    n = mesh.vertex_normals[v]
    a, b = mesh.vertices[u] - mesh.vertices[v], mesh.vertices[x] - mesh.vertices[v]
    a, b = a - n * a.dot(n), b - n * b.dot(n)
    return float((np.arctan2(np.cross(b, a).dot(n), a.dot(b))) % (2 * np.pi))


def fill_loop(vertices, loop, existing):
    """Minimal-area triangulation of the hole ``loop`` (vertex indices, in
    the hole's direction) using only its own corners; no triangle with a
    corner twice and no chord that is already an edge (``existing``: set
    of sorted vertex pairs).  Returns (k, 3) vertex indices oriented like
    the surface around, or None when there is no such triangulation."""
    n = len(loop)
    if n < 3 or n > MAX_LOOP_CORNERS:
        return None
    p = vertices[loop]
    ids = np.asarray(loop)
    ok = np.ones((n, n), dtype=bool)             # chord i-j allowed
    for i in range(n):
        for j in range(i + 2, n):
            if (i, j) == (0, n - 1):
                continue
            a, b = loop[i], loop[j]
            if a == b or (min(a, b), max(a, b)) in existing:
                ok[i, j] = False
    cost = np.full((n, n), np.inf)
    best = np.zeros((n, n), dtype=np.int64)
    for i in range(n - 1):
        cost[i, i + 1] = 0.0
    for gap in range(2, n):
        for i in range(0, n - gap):
            j = i + gap
            if not ok[i, j] or ids[i] == ids[j]:
                continue
            k = np.arange(i + 1, j)
            area = 0.5 * np.linalg.norm(np.cross(p[k] - p[i], p[j] - p[i]), axis=1)
            bad = (ids[k] == ids[i]) | (ids[k] == ids[j])
            total = cost[i, k] + cost[k, j] + np.where(bad, np.inf, area)
            m = int(np.argmin(total))
            cost[i, j], best[i, j] = total[m], k[m]
    if not np.isfinite(cost[0, n - 1]):
        return None
    out, stack = [], [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        k = int(best[i, j])
        out.append((loop[i], loop[k], loop[j]))
        stack += [(i, k), (k, j)]
    return np.array(out, dtype=np.int64)


def _fill_pinched(mesh):
    """Fill, each on its own, the hole loops that pass through a vertex
    where holes touch (:func:`hole_loops`, :func:`fill_loop`).  Returns
    (mesh with those loops filled, added (k, 3, 3) triangles, loops
    filled); ``mesh`` itself and no triangles when no holes touch."""
    loops, pinch = hole_loops(mesh)
    if not len(pinch):
        return mesh, np.zeros((0, 3, 3)), 0
    touching = [loop for loop in loops if np.isin(loop, pinch).any()]
    existing = set(map(tuple, np.sort(mesh.edges_unique, axis=1).tolist()))
    new, n_filled = [], 0
    for loop in touching:
        tri = fill_loop(mesh.vertices, loop, existing)
        if tri is None:
            continue                             # left to MeshFix (and to the check after it)
        existing.update(map(tuple, np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]),
                                           axis=1).tolist()))
        new.append(tri)
        n_filled += 1
    if not new:
        return mesh, np.zeros((0, 3, 3)), 0
    new = np.concatenate(new)
    filled = trimesh.Trimesh(mesh.vertices, np.concatenate([mesh.faces, new]), process=False)
    return filled, mesh.vertices[new], n_filled



def nonmanifold_edges(mesh):
    """Number of edges used by more than two triangles."""
    edges = np.sort(mesh.edges_sorted, axis=1) if len(mesh.faces) else np.zeros((0, 2), int)
    if not len(edges):
        return 0
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts > 2).sum())


def open_edges(mesh):
    """Number of edges used by exactly one triangle."""
    return len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))


def _patch(before, after):
    """Indices of the triangles of ``after`` not in ``before`` (added) and
    of ``before`` not in ``after`` (removed); triangles are matched by their
    corners' coordinates."""
    # one id per distinct corner position over both meshes
    _, ids = np.unique(np.round(np.concatenate([before.vertices, after.vertices]), 9), axis=0,
                       return_inverse=True)
    ids = ids.reshape(-1)
    kb = np.sort(ids[:len(before.vertices)][before.faces], axis=1)
    ka = np.sort(ids[len(before.vertices):][after.faces], axis=1)
    # one id per distinct triangle (its sorted corner ids) over both meshes
    _, tri = np.unique(np.concatenate([kb, ka]), axis=0, return_inverse=True)
    tri = tri.reshape(-1)
    tb, ta = tri[:len(kb)], tri[len(kb):]
    added = np.flatnonzero(~np.isin(ta, tb))
    removed = np.flatnonzero(~np.isin(tb, ta))
    return added, removed


def solid_angle_sum(points, triangles):
    """Sum of the signed solid angles (sr) of ``triangles`` ((m, 3, 3), mm)
    seen from ``points`` ((n, 3), mm): the generalized winding number times
    4 pi (Van Oosterom & Strackee 1983).  Returns (n,)."""
    total = np.zeros(len(points))
    if not len(triangles):
        return total
    step = max(1, 2_000_000 // len(triangles))
    for s in range(0, len(points), step):
        p = points[s:s + step, None, None, :]
        r = triangles[None, :, :, :] - p                 # (k, m, 3, 3)
        a, b, c = r[:, :, 0], r[:, :, 1], r[:, :, 2]
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        det = np.einsum("kmi,kmi->km", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("kmi,kmi->km", a, b) * lc
               + np.einsum("kmi,kmi->km", b, c) * la + np.einsum("kmi,kmi->km", c, a) * lb)
        total[s:s + step] = 2.0 * np.arctan2(det, den).sum(axis=1)
    return total


def winding_volume(closed, added, removed, samples=WINDING_SAMPLES):
    """Volume (mm^3) the open mesh ``closed - added + removed`` encloses,
    hole by hole (see the module text).

    For each hole, the points whose winding number with respect to the
    model with only that hole open is >= 0.5: ``closed`` minus the volume
    that hole's patch changes.  Holes are judged one at a time because the
    deficits of several holes add up: an open bottom and a small hole in the
    top of a flat box would push a thin slab above the bottom under 0.5.

    ``closed``: the repaired, watertight, outward mesh; ``added`` and
    ``removed``: what the repair added to and removed from the open mesh;
    ``samples``: stratified points, shared by the holes."""
    patch = np.concatenate([added.vertices[added.faces], removed.vertices[removed.faces][:, ::-1]])
    if not len(patch):
        return float(closed.volume)
    holes = _patches(patch)
    pad = 1e-3 * float(np.linalg.norm(closed.extents))
    n = max(2, int(round((samples / len(holes)) ** (1.0 / 3.0))))
    # stratified: one jittered point per cell of an n^3 grid per hole (fixed seed: repeatable)
    cells = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    points, boxes = [], []
    for tri in holes:
        lo = np.maximum(tri.reshape(-1, 3).min(axis=0) - pad, closed.bounds[0] - pad)
        hi = np.minimum(tri.reshape(-1, 3).max(axis=0) + pad, closed.bounds[1] + pad)
        points.append(lo + (cells + rng.random(cells.shape)) / n * (hi - lo))
        boxes.append(float(np.prod(hi - lo)))
    winding = closed_winding(closed, np.concatenate(points)).reshape(len(holes), -1)
    change = 0.0
    for tri, p, box, w in zip(holes, points, boxes, winding):
        w_patch = solid_angle_sum(p, tri) / (4.0 * np.pi)
        change += box * float(np.mean((w >= 0.5).astype(float) - ((w - w_patch) >= 0.5)))
    return float(closed.volume) - change


def closed_winding(closed, points):
    """Winding number of the closed mesh ``closed`` at ``points`` ((n, 3),
    mm): per shell, +1 inside an outward one, -1 inside a cavity, summed
    (shells that overlap count twice where they overlap).  Returns (n,)."""
    bodies = closed.split(only_watertight=False) if closed.body_count > 1 else [closed]
    lo, hi = points.min(axis=0), points.max(axis=0)
    w = np.zeros(len(points))
    for body in bodies:
        if (body.bounds[0] > hi).any() or (body.bounds[1] < lo).any():
            continue
        w += np.sign(body.volume) * body.contains(points)
    return w


def _patches(triangles):
    """``triangles`` ((m, 3, 3), mm) grouped into the connected patches
    (corners shared), one (k, 3, 3) array per patch: one per hole."""
    labels = _patch_labels(triangles)
    return [triangles[labels == k] for k in np.unique(labels)]


def _patch_labels(triangles):
    """A label per triangle of ``triangles`` ((m, 3, 3)): its connected
    patch (triangles sharing a corner, by coordinates)."""
    _, ids = np.unique(np.round(triangles.reshape(-1, 3), 9), axis=0, return_inverse=True)
    faces = ids.reshape(-1, 3)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    labels = trimesh.graph.connected_component_labels(edges, node_count=int(ids.max()) + 1)
    return labels[faces[:, 0]]
