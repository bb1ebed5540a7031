"""Surfaces that cross themselves: pairs of triangles of a mesh that
intersect without sharing a corner (inside one shell or between shells).
:mod:`ambots.mesh` refuses such a model, naming where
(:func:`ambots.mesh.check_self_intersection`); the cost against MeshFix's
own check is in docs/pipeline.md."""
import numpy as np

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
    sharing a cell whose boxes overlap; narrow phase: each of the six edges
    of a pair against the other triangle (Moller-Trumbore), in numpy.  Hits
    within 1e-9 of the model's size of an edge's end or of the other
    triangle's border do not count: triangles that only touch are not
    crossing (two coplanar triangles that overlap are not found either)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(tri) < 2:
        return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 3))
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    size = float(np.linalg.norm(mesh.extents)) or 1.0
    cell = max(float(np.mean(hi - lo)) * 2.0, 1e-6 * size)
    c_lo = np.floor((lo - lo.min(axis=0)) / cell).astype(np.int64)
    c_hi = np.floor((hi - lo.min(axis=0)) / cell).astype(np.int64)
    span = c_hi - c_lo + 1
    # one (cell, triangle) row per cell a triangle's box covers
    count = np.prod(span, axis=1)
    owner = np.repeat(np.arange(len(tri)), count)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
    sx, sy = span[owner, 0], span[owner, 1]
    ijk = c_lo[owner] + np.stack([k % sx, (k // sx) % sy, k // (sx * sy)], axis=1)
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    lengths = np.diff(np.concatenate([starts, [len(key)]]))
    eps = 1e-9 * size
    lo_cols = [np.ascontiguousarray(lo[:, axis]) for axis in range(3)]
    hi_cols = [np.ascontiguousarray(hi[:, axis]) for axis in range(3)]
    corners = [np.ascontiguousarray(faces[:, i]) for i in range(3)]
    pairs = []
    for m in np.unique(lengths[lengths > 1]):          # cells of m triangles: all pairs at once
        i, j = np.triu_indices(int(m), 1)
        cells = starts[lengths == m]
        step = max(1, 500_000 // len(i))              # bounded memory: ~500,000 pairs at a time
        for c in range(0, len(cells), step):
            members = owner[cells[c:c + step, None] + np.arange(m)]      # (cells, m)
            a, b = members[:, i].ravel(), members[:, j].ravel()
            keep = np.ones(len(a), dtype=bool)
            for lo_, hi_ in zip(lo_cols, hi_cols):    # boxes overlap (column by column: 5x faster)
                keep &= (lo_[a] <= hi_[b] + eps) & (lo_[b] <= hi_[a] + eps)
            a, b = a[keep], b[keep]
            share = np.zeros(len(a), dtype=bool)      # neighbours (a corner in common) do not count
            of_b = [cb[b] for cb in corners]
            for ca in corners:
                ca = ca[a]
                for cb in of_b:
                    share |= ca == cb
            pairs.append(np.sort(np.stack([a[~share], b[~share]], axis=1), axis=1))
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


