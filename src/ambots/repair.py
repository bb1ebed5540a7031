"""Mesh repair: close the holes of an open mesh when the defect is small.

CAD exports and scans often miss a few triangles or leave a face open.  The
holes are closed by MeshFix (``pymeshfix``, the low-level ``PyTMesh``
binding: no pyvista), which fills every boundary loop with a triangulation
of the loop's own corners (no refinement: no new vertices).  trimesh's own ``fill_holes`` closes
only holes of 3 or 4 edges; manifold3d needs a closed mesh to start with.

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
        for k in ("fill_area_mm2", "volume_before_mm3", "volume_after_mm3"):
            if out[k] is not None:
                out[k] = round(float(out[k]), 3)
        for k in ("fill_area_share", "volume_change"):
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
    if report.get("shells_merged"):
        parts.append("%d overlapping shells merged" % report["shells_merged"])
    line = "repaired: " + "; ".join(parts)
    if report.get("volume_before_mm3") is not None and report.get("holes_closed"):
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
        closed, added, removed, report.holes_closed = _fill(mesh)
    except Exception as exc:  # noqa: BLE001 -- boundary to a third-party C++ library
        report.notes.append("MeshFix failed (%s: %s); holes left open" % (type(exc).__name__, exc))
        report.open_edges_after = report.open_edges_before
        return mesh.copy()               # validate_mesh refuses it, with the open-edge count
    report.open_edges_after = open_edges(closed)
    pinched = nonmanifold_edges(closed)
    if pinched:                          # holes that touch each other: MeshFix's fill is not a surface
        report.notes.append("MeshFix's fill left %d edges shared by more than two triangles" % pinched)
        raise MeshError("%s: not a closed volume: %d open edges; closing them gives %d edges shared by more "
                        "than two triangles (holes that touch each other at a corner or an edge): not "
                        "repaired" % (name, report.open_edges_before, pinched))
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
    Trimeshes keeping their orientation.

    Large meshes: MeshFix gets the triangles within two rings of the holes;
    the patches it also puts on that region's own outer border (no hole of
    the model) are dropped, the others added to the whole mesh."""
    from pymeshfix import PyTMesh
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
    closed = trimesh.Trimesh(np.concatenate([mesh.vertices, triangles.reshape(-1, 3)]),
                             np.concatenate([mesh.faces[keep],
                                             len(mesh.vertices) + np.arange(3 * len(triangles)).reshape(-1, 3)]),
                             process=False)
    closed.merge_vertices()
    closed.remove_unreferenced_vertices()
    return (closed, trimesh.Trimesh(triangles.reshape(-1, 3), np.arange(3 * len(triangles)).reshape(-1, 3),
                                    process=False),
            trimesh.Trimesh(mesh.vertices, mesh.faces[region[removed]], process=False), n_filled)


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
