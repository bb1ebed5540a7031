"""Surfaces that cross themselves: pairs of triangles of a mesh that
intersect without sharing a corner (inside one shell or between shells),
found by :func:`crossing_pairs` / :func:`self_intersections`, and repaired
when the defect is small by :func:`repair_crossings` (its rule:
:func:`crossing_rule_text`); :mod:`ambots.mesh` refuses the rest, naming
where and the figure that failed.  The costs are in docs/pipeline.md."""
import numpy as np
import trimesh

from ambots.errors import MeshError
from ambots.repair import MAX_VOLUME_CHANGE, _fill, _patch, nonmanifold_edges, open_edges, winding_volume

def self_intersections(mesh, first=10):
    """Pairs of triangles of ``mesh`` that cross each other and share no
    corner (a self-intersection, inside one shell or between shells).
    Returns (n pairs found, up to ``first`` distinct points (k, 3), mm, where
    an edge of one triangle of a pair passes through the other); how: see
    :func:`crossing_pairs`."""
    pairs, point = crossing_pairs(mesh)
    if not len(pairs):
        return 0, np.zeros((0, 3))
    eps = 1e-9 * (float(np.linalg.norm(mesh.extents)) or 1.0)
    _, at = np.unique(np.round(point / eps), axis=0, return_index=True)
    return len(pairs), point[np.sort(at)][:first]     # distinct points, in pair order


def crossing_pairs(mesh):
    """The pairs of triangles of ``mesh`` that cross each other and share
    no corner: (pairs (n, 2) face indices, points (n, 3) mm: for each pair,
    where an edge of one passes through the other).

    Broad phase: a uniform grid of cells about the mean triangle size, every
    triangle in the cells its bounding box covers, candidate pairs those
    sharing a cell whose boxes overlap (boxes widened by the tolerance and
    rounded outward to float32); narrow phase: each of the six edges
    of a pair against the other triangle (Moller-Trumbore), in numpy.  Hits
    within 1e-9 of the model's size of an edge's end or of the other
    triangle's border do not count: triangles that only touch are not
    crossing (two coplanar triangles that overlap are not found either)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(tri) < 2:
        return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 3))
    # corner by corner: 10x faster than min/max over the middle axis
    lo = np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2])
    hi = np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2])
    size = float(np.linalg.norm(mesh.extents)) or 1.0
    cell = max(float(np.mean(hi - lo)) * 2.0, 1e-6 * size)
    c_lo = np.floor((lo - lo.min(axis=0)) / cell).astype(np.int64)
    c_hi = np.floor((hi - lo.min(axis=0)) / cell).astype(np.int64)
    span = c_hi - c_lo + 1
    dims = c_hi.max(axis=0) + 1
    # one (cell, triangle) row per cell a triangle's box covers, the cell as
    # one integer; a box of at most 2 cells an axis (most): one pass per
    # offset in the 2 x 2 x 2 block; larger boxes: cell by cell
    base = (c_lo[:, 0] * dims[1] + c_lo[:, 1]) * dims[2] + c_lo[:, 2]
    small = (span <= 2).all(axis=1)
    by_cell = np.argsort(base)            # each pass's rows come sorted: one merge of runs below
    keys, owners = [], []
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                at = by_cell[(small & (span[:, 0] > dx) & (span[:, 1] > dy) & (span[:, 2] > dz))[by_cell]]
                keys.append(base[at] + (dx * dims[1] + dy) * dims[2] + dz)
                owners.append(at)
    large = np.flatnonzero(~small)
    if len(large):
        count = np.prod(span[large], axis=1)
        owner = np.repeat(large, count)
        k = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
        sx, sy = span[owner, 0], span[owner, 1]
        ijk = c_lo[owner] + np.stack([k % sx, (k // sx) % sy, k // (sx * sy)], axis=1)
        keys.append((ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2])
        owners.append(owner)
    key, owner = np.concatenate(keys), np.concatenate(owners)
    # a merge of the sorted runs (timsort finds them); the order inside a cell
    # does not matter: pairs are sorted below
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    lengths = np.diff(np.concatenate([starts, [len(key)]]))
    eps = 1e-9 * size
    # boxes in float32 rounded outward (half the memory to gather; the
    # candidates a superset of the float64 test's: the narrow phase decides)
    lo_cols = [np.nextafter((lo[:, axis] - eps).astype(np.float32), np.float32(-np.inf)) for axis in range(3)]
    hi_cols = [np.nextafter((hi[:, axis] + eps).astype(np.float32), np.float32(np.inf)) for axis in range(3)]
    corners = [np.ascontiguousarray(faces[:, i], dtype=np.int32 if len(mesh.vertices) < 2 ** 31 else np.int64)
               for i in range(3)]
    pairs = []
    for m in np.unique(lengths[lengths > 1]):          # cells of m triangles: all pairs at once
        i, j = np.triu_indices(int(m), 1)
        cells = starts[lengths == m]
        step = max(1, 500_000 // len(i))              # bounded memory: ~500,000 pairs at a time
        for c in range(0, len(cells), step):
            members = owner[cells[c:c + step, None] + np.arange(m)]      # (cells, m)
            # each member's data gathered once, (cells, m), then paired inside its row
            keep = np.ones((len(members), len(i)), dtype=bool)
            for lo_, hi_ in zip(lo_cols, hi_cols):    # boxes overlap (column by column: 5x faster)
                lo_m, hi_m = lo_[members], hi_[members]
                keep &= (lo_m[:, i] <= hi_m[:, j]) & (lo_m[:, j] <= hi_m[:, i])
            at = np.flatnonzero(keep)                 # flat indices into members: 1-D takes are faster
            row, col = np.divmod(at, len(i))
            fa, fb = row * m + i[col], row * m + j[col]
            share = np.zeros(len(at), dtype=bool)     # neighbours (a corner in common) do not count
            corner_m = [cm[members].ravel() for cm in corners]
            of_b = [cm.take(fb) for cm in corner_m]
            for cm in corner_m:
                ca = cm.take(fa)
                for cb in of_b:
                    share |= ca == cb
            flat = members.ravel()
            pairs.append(np.sort(np.stack([flat.take(fa[~share]), flat.take(fb[~share])], axis=1), axis=1))
    pairs = np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)
    key = np.unique(pairs[:, 0] * len(tri) + pairs[:, 1])        # a pair met in several cells: once
    pairs = np.stack([key // len(tri), key % len(tri)], axis=1)
    if not len(pairs):
        return pairs, np.zeros((0, 3))
    hit = np.zeros(len(pairs), dtype=bool)
    point = np.zeros((len(pairs), 3))
    for one, other in ((0, 1), (1, 0)):
        t1, t2 = tri[pairs[:, one]], tri[pairs[:, other]]
        for e in range(3):
            p, q = t1[:, e], t1[:, (e + 1) % 3]
            crossed, where = _segment_crosses(p, q, t2, eps)
            new = crossed & ~hit
            point[new] = where[new]
            hit |= crossed
    return pairs[hit], point[hit]


def _segment_crosses(p, q, tri, eps):
    """Whether segments p-q ((n, 3)) pass through the inside of the
    triangles ``tri`` ((n, 3, 3)), and where."""
    d = q - p
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = p - tri[:, 0]
        u = np.einsum("ij,ij->i", s, h) * inv
        qv = np.cross(s, e1)
        v = np.einsum("ij,ij->i", d, qv) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
        # tolerances in lengths: along the segment, and from the triangle's borders
        length = np.linalg.norm(d, axis=1)
        tol_t = eps / np.maximum(length, eps)
        ok = (np.abs(det) > 1e-12 * np.maximum(length, eps) * np.linalg.norm(e1, axis=1)
              * np.linalg.norm(e2, axis=1))
        # barycentric tolerance: eps over the triangle's smallest height
        area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
        longest = np.max(np.linalg.norm(np.stack([e1, e2, e2 - e1], 1), axis=2), axis=1)
        tol_b = eps * longest / np.maximum(area2, eps * eps)
        crossed = ok & (t > tol_t) & (t < 1 - tol_t) & (u > tol_b) & (v > tol_b) & (u + v < 1 - tol_b)
    return crossed, p + d * np.where(crossed, t, 0.0)[:, None]


# ------------------------------------------------ a surface crossing itself

#: most of the surface the repair of a self-crossing surface may change
#: (triangles removed, as a share of the original surface area)
MAX_CROSSING_AREA_SHARE = 0.05
#: rounds of "remove the crossing triangles and a ring, fill the holes"
CROSSING_ROUNDS = 3


def repair_crossings(mesh, name, report, pairs, points, notes):
    """Repair a closed surface that crosses itself (``pairs``, ``points``:
    :func:`ambots.selfcross.crossing_pairs`) when the defect is small;
    return the repaired mesh (a new Trimesh), fill ``report`` and append
    the repair in words to ``notes``.

    Two ways are tried, the first whose result keeps the rule wins:

    1. MeshFix's own clean-up (``PyTMesh.clean``: it removes the triangles
       that cross and fills the holes; it changes the fewest triangles);
    2. :func:`_cut_and_fill`: the triangles of the crossing pairs and a
       ring around them removed, the holes filled (:func:`_fill`), up to
       :data:`CROSSING_ROUNDS` rounds.

    **The rule**: the result is watertight, consistently oriented, has as
    many bodies as before and does not cross itself; the triangles removed
    are at most :data:`MAX_CROSSING_AREA_SHARE` of the surface area; the
    volume after is within :data:`MAX_VOLUME_CHANGE` of the original's
    winding-number volume (the points whose generalized winding number is
    >= 0.5: the solid the crossing surface means, each place counted once;
    :func:`winding_volume`, sampled near the change only).
    Raises MeshError naming ``name``, where, and the figure that failed."""
    where = ", ".join("(%.2f, %.2f, %.2f)" % tuple(p) for p in _distinct(points, mesh)[:3]) + \
        (", ..." if len(pairs) > 3 else "")
    head = ("%s: the surface crosses itself: %d pair%s of triangles intersect, at %s mm (the model's frame)"
            % (name, len(pairs), "" if len(pairs) == 1 else "s", where))
    report.crossing_pairs = len(pairs)
    report.rule = (report.rule + "; " if report.rule else "") + "crossings: " + crossing_rule_text()
    tried = []
    for method, attempt in (("pymeshfix (MeshFix) clean", _meshfix_clean),
                            ("crossing triangles and a ring removed, holes filled by pymeshfix (MeshFix)",
                             lambda m: _cut_and_fill(m, pairs))):
        try:
            current = attempt(mesh)
        except Exception as exc:  # noqa: BLE001 -- boundary to a third-party C++ library
            tried.append("%s: failed (%s: %s)" % (method, type(exc).__name__, exc))
            continue
        why, figures = _judge(mesh, current)
        if why:
            tried.append("%s: %s" % (method, why))
            continue
        added, gone, area, before, after = figures
        report.method = (report.method + "; " if report.method else "") + "crossings: " + method
        report.crossing_area_mm2 = area
        report.crossing_area_share = area / float(mesh.area)
        report.faces_added += len(added.faces)
        report.faces_removed += len(gone.faces)
        if report.volume_before_mm3 is None:
            report.volume_before_mm3 = before
        report.volume_after_mm3 = after
        report.volume_change = (after - report.volume_before_mm3) / report.volume_before_mm3
        notes.append("surface crossed itself at %s mm: %d pair%s of triangles, repaired by %s: %d "
                            "triangles removed (%.2f mm^2, %.2f %% of the surface), %d added; volume %.1f "
                            "(winding number) -> %.1f mm^3"
                            % (where, len(pairs), "" if len(pairs) == 1 else "s", method, len(gone.faces),
                               area, 100 * report.crossing_area_share, len(added.faces), before, after))
        return current
    raise MeshError("%s: not repaired: %s (the rule: %s)" % (head, "; ".join(tried), crossing_rule_text()))


def _judge(mesh, current):
    """(why the repair ``current`` of ``mesh`` breaks the rule or None,
    (added, removed, removed area, volume before, volume after))."""
    if open_edges(current) or nonmanifold_edges(current) or not current.is_winding_consistent:
        return ("the result is not a closed oriented surface (%d open, %d non-manifold edges)"
                % (open_edges(current), nonmanifold_edges(current)), None)
    with np.errstate(divide="ignore", invalid="ignore"):
        if current.volume < 0:
            current.invert()
    added, gone = _patch(mesh, current)
    area = float(mesh.area_faces[gone].sum())
    share = area / float(mesh.area) if mesh.area > 0 else 1.0
    if share > MAX_CROSSING_AREA_SHARE:
        return ("it removes %.1f mm^2, %.1f %% of the surface, more than %g %%"
                % (area, 100 * share, 100 * MAX_CROSSING_AREA_SHARE), None)
    if current.body_count != mesh.body_count:
        return "%d bodies before, %d after" % (mesh.body_count, current.body_count), None
    left = len(crossing_pairs(current)[0])
    if left:
        return "%d pairs still cross" % left, None
    added = trimesh.Trimesh(current.vertices, current.faces[added], process=False)
    gone = trimesh.Trimesh(mesh.vertices, mesh.faces[gone], process=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        before, after = winding_volume(current, added, gone), float(current.volume)
    change = (after - before) / before if before > 0 else float("inf")
    if abs(change) > MAX_VOLUME_CHANGE:
        return ("it changes the volume from %.1f mm^3 (winding number >= 0.5) to %.1f mm^3 (%+.1f %%), "
                "more than %g %%" % (before, after, 100 * change, 100 * MAX_VOLUME_CHANGE), None)
    return None, (added, gone, area, before, after)


def _meshfix_clean(mesh):
    """MeshFix's removal of self-intersections (``PyTMesh.clean``)."""
    from pymeshfix import PyTMesh
    fixer = PyTMesh(False)
    fixer.load_array(np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                     np.ascontiguousarray(mesh.faces, dtype=np.int32))
    fixer.clean(max_iters=10, inner_loops=3)
    return trimesh.Trimesh(*fixer.return_arrays(), process=False)


def _cut_and_fill(mesh, pairs):
    """Remove the triangles of the crossing ``pairs`` and those sharing a
    corner with them, fill the holes (:func:`_fill`); again with a wider
    ring while the result still crosses itself (:data:`CROSSING_ROUNDS`)."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    drop = np.zeros(len(faces), dtype=bool)
    current, found = mesh, pairs
    for rounds in range(1, CROSSING_ROUNDS + 1):
        drop[_original_faces(mesh, current, found.ravel())] = True
        for _ in range(rounds):                 # the ring: faces sharing a corner, wider each round
            drop |= np.isin(faces, faces[drop]).any(axis=1)
        if drop.all():
            raise ValueError("every triangle would be removed")
        current = _fill(trimesh.Trimesh(mesh.vertices, faces[~drop], process=False))[0]
        if open_edges(current) or nonmanifold_edges(current):
            break
        found = crossing_pairs(current)[0]
        if not len(found):
            break
    return current


def crossing_rule_text():
    """The rule for a surface that crosses itself, in words."""
    return ("closed, oriented, as many bodies and no crossing after; triangles removed <= %g %% of the "
            "surface area; volume within %g %% of the original's (winding number >= 0.5)"
            % (100 * MAX_CROSSING_AREA_SHARE, 100 * MAX_VOLUME_CHANGE))


def _distinct(points, mesh):
    """``points`` without repeats (within 1e-9 of the model's size), in order."""
    if not len(points):
        return points
    eps = 1e-9 * (float(np.linalg.norm(mesh.extents)) or 1.0)
    _, at = np.unique(np.round(points / eps), axis=0, return_index=True)
    return points[np.sort(at)]


def _original_faces(original, current, index):
    """Indices of the triangles of ``original`` that are triangles
    ``index`` of ``current`` (by their corners' coordinates); those not in
    ``original`` (fill) give the original triangles sharing a corner with them."""
    if current is original:
        return np.unique(index)
    _, ids = np.unique(np.round(np.concatenate([original.vertices, current.vertices]), 9), axis=0,
                       return_inverse=True)
    ids = ids.reshape(-1)
    corners = np.unique(ids[len(original.vertices):][current.faces[np.unique(index)]])
    return np.flatnonzero(np.isin(ids[:len(original.vertices)][original.faces], corners).any(axis=1))
