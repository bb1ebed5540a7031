"""Seams between the arms' parts: the layer-by-layer interlock, and how much
of a seam's face the deposit bonds.

**Interlock.**  Two arms' parts that simply meet at a vertical plane (the
``straight`` seam) are two walls printed side by side: the plane carries a
junction of two beads that merely touch on every layer, the weakest plane
of the print.  The interlock staggers the junction layer by layer, as
masonry staggers its joints: on even layers (the slicer's, counted from
the bed) the part of the lower-indexed arm of every pair reaches ``d``
past the plane and its neighbour stops there; on odd layers the other way
round.  Each layer's junction then lies ``2 d`` away from the junctions of
the layers above and below, which bridge it, and each arm's layer laps the
other arm's layers above and below over ``2 d`` (an interlayer bond across
the seam, like Cura's and PrusaSlicer's multi-material interlocking, which
alternate the owner of the boundary band every few layers).  With several
arms the order of the arms is reversed every layer: the earlier arm in the
order takes its cell grown by ``d`` into every later arm's, minus what the
earlier arms took, so the parts of one layer always tile it.

``d`` (:func:`interlock_depth_mm`) is half a bead plus one bead spacing:
the centre line of the second perimeter from the boundary.  So on every
layer the seam plane runs along the middle of one wall bead of whichever
arm owns that layer there (bonded, with margin), the band of ``2 d`` around
the plane is wall or solid skin on both sides (the slicer sees the steps as
tops and bottoms), and no perimeter junction of one layer lies on another
layer's.  The slabs follow the slicer's layers
(:func:`ambots.slicer.layer_heights`), so each sliced layer falls wholly in
one slab.

**Bonded share** (:func:`bonded_share`): the seam face between two parts
(the seam plane inside the model where those two parts meet) sampled at
every layer's mid-height, one point every ``step_mm`` along the seam; a
point is bonded when one bead's box (:mod:`ambots.deposit`) contains the
two points a quarter bead width on either side of it (material continuous
across the plane), not bonded when the plane only runs where beads meet
side by side, or through a gap.

Units: millimetres in the bed frame (the G-code frame).
"""
import numpy as np

from ambots.seam_steps import offset_at

__all__ = ["SEAMS", "seam_kind", "interlock_depth_mm", "interlock_pieces", "seam_samples", "bonded_mask",
           "bonded_share", "deposit_beads_mm", "lap_order", "seam_setup", "seam_figures", "beads_in_bed_mm",
           "placed_model"]

#: the seams a job takes (``overlap``: the issue's name of the interlock)
SEAMS = ("straight", "interlock", "overlap")


def seam_kind(seam):
    """``straight`` or ``interlock`` (``overlap`` is the interlock);
    ValueError naming the field otherwise."""
    if seam not in SEAMS:
        raise ValueError("seam must be one of %s, got %r" % (", ".join(SEAMS), seam))
    return "straight" if seam == "straight" else "interlock"


def interlock_depth_mm(bead_width, layer_height):
    """How far past the seam plane a part reaches on its layers, mm: half a
    bead plus one bead spacing (the slicer's, ``w - h (1 - pi/4)``), the
    centre line of a part's second perimeter."""
    return bead_width / 2.0 + (bead_width - layer_height * (1.0 - np.pi / 4.0))


def _slabs(z_tops, heights, lo, hi, parity):
    """One manifold of the layers of ``parity`` (0: even, 1: odd) as boxes
    over the xy box ``lo``..``hi`` (mm); the first layer reaches down to
    below the model, the last up above it."""
    import manifold3d as m3
    # boundaries on a grid of 2^-20 mm, so z0 + (z1 - z0) is z1 exactly and
    # neighbouring slabs touch without a sliver between them
    grid = lambda z: float(np.round(z * 2.0 ** 20) / 2.0 ** 20)
    boxes = []
    for k in range(parity, len(z_tops), 2):
        z0 = grid(z_tops[k - 1]) if k > 0 else -1e4
        z1 = grid(z_tops[k]) if k < len(z_tops) - 1 else 1e4
        boxes.append(m3.Manifold.cube([hi[0] - lo[0], hi[1] - lo[1], z1 - z0]).translate([lo[0], lo[1], z0]))
    if not boxes:
        return m3.Manifold()
    return m3.Manifold.batch_boolean(boxes, m3.OpType.Add) if len(boxes) > 1 else boxes[0]


def _clip(poly, nrm, off):
    """The convex polygon ``poly`` (K, 2) cut to n . p >= off (Sutherland-Hodgman)."""
    out = []
    n2 = np.asarray(nrm, dtype=float)[:2]
    for p, q in zip(poly, np.roll(poly, -1, axis=0)):
        dp, dq = p @ n2 - off, q @ n2 - off
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            out.append(p + dp / (dp - dq) * (q - p))
    return np.array(out).reshape(-1, 2)


#: pieces of a layer's cell smaller than this (mm^2) are slivers left by the
#: booleans where several cells meet, not material: dropped
SLIVER_MM2 = 1e-3


def _solid(cs):
    """``cs`` (CrossSection) without its sliver pieces (:data:`SLIVER_MM2`)."""
    import manifold3d as m3
    pieces = [p for p in cs.decompose() if p.area() >= SLIVER_MM2]
    return m3.CrossSection.batch_boolean(pieces, m3.OpType.Add) if pieces else m3.CrossSection()


def _ordered_cells(rect, planes, order, d):
    """The layer's cells (manifold3d.CrossSection, xy mm) for one order of
    the parts: part ``m`` keeps its half-planes ``planes[m]`` ([(n, off)],
    one per other part in index order) inside the rectangle ``rect`` (4, 2),
    grown by ``d`` towards the parts after it in ``order``, minus what the
    parts before it took.  A list in part index order; they tile ``rect``."""
    import manifold3d as m3
    n_parts = len(planes)
    out, taken = [None] * n_parts, None
    for rank, m in enumerate(order):
        later = set(order[rank + 1:])
        others = [j for j in range(n_parts) if j != m]
        poly = np.asarray(rect, dtype=float)
        for j, (nrm, off) in zip(others, planes[m]):
            poly = _clip(poly, nrm, float(off) - (d if j in later else 0.0))
        cell = m3.CrossSection([poly.tolist()]) if len(poly) >= 3 else m3.CrossSection()
        if taken is not None:
            cell = _solid(cell - taken)
        out[m] = cell
        taken = cell if taken is None else taken + cell
    return out


def interlock_pieces(model, planes, d, z_tops, heights):
    """The parts of an interlocking seam: ``model`` (manifold3d.Manifold,
    mm), ``planes[i]`` part i's half-spaces of the power diagram ([(n, off)]
    kept side n . p >= off, one per other part in index order), ``d`` mm,
    the slicer's layers ``z_tops``, ``heights`` (L,) mm.  On even layers
    the arms' order is 0, 1, ..., on odd layers reversed (see the module
    docstring).  Returns one closed Manifold per part; they tile the model.

    Each part is the model cut to (its cell on every layer, a prism) plus
    (its even-layer cell x the even slabs) plus (its odd-layer cell x the
    odd slabs): the slabs of one part that touch also overlap that prism,
    so the part is one solid, not slabs resting on each other."""
    import manifold3d as m3
    bb = model.bounding_box()
    lo, hi = np.array(bb[:2]) - 10.0, np.array(bb[3:5]) + 10.0
    rect = [[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]
    n_parts = len(planes)
    even = _ordered_cells(rect, planes, list(range(n_parts)), d)
    odd = _ordered_cells(rect, planes, list(range(n_parts))[::-1], d)
    slabs = [_slabs(z_tops, heights, lo, hi, parity) for parity in (0, 1)]
    prism = lambda cs: m3.Manifold.extrude(cs, 2e4).translate([0.0, 0.0, -1e4])
    out = []
    for e, o in zip(even, odd):
        region = m3.Manifold.batch_boolean([prism(_solid(e ^ o)), slabs[0] ^ prism(e), slabs[1] ^ prism(o)],
                                           m3.OpType.Add)
        part = model ^ region
        pieces = part.decompose()
        if len(pieces) > 1:          # a boolean's zero-volume sliver where three cells meet: not material
            keep = [q for q in pieces if q.volume() >= SLIVER_MM2 * 1e-3]
            part = m3.Manifold.batch_boolean(keep, m3.OpType.Add) if keep else m3.Manifold()
        out.append(part)
    return out


# ------------------------------------------------------------ bonded share

def _join_pieces(S, E, W, H, tol_mm=1e-3, cos_min=0.9999):
    """Consecutive beads that continue one another (the next starts where
    this one ends, in the same direction, as wide and as high) joined into
    one: the runners lay a G-code move as several pieces, one extrusion.
    Arrays as :func:`deposit_beads_mm`'s, one arm's, in laying order."""
    if len(S) < 2:
        return S, E, W, H
    d = E - S
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    cont = ((np.linalg.norm(S[1:] - E[:-1], axis=1) <= tol_mm) & (np.sum(u[1:] * u[:-1], axis=1) >= cos_min)
            & (np.abs(W[1:] - W[:-1]) <= 0.02 * W[:-1]) & (np.abs(H[1:] - H[:-1]) <= 1e-6))
    first = np.concatenate([[True], ~cont])
    start = np.flatnonzero(first)
    last = np.concatenate([start[1:] - 1, [len(S) - 1]])
    L = np.linalg.norm(d, axis=1)
    width = np.add.reduceat(W * L, start) / np.maximum(np.add.reduceat(L, start), 1e-12)
    return S[start], E[last], width, H[start]


def deposit_beads_mm(deposit, bed_pose):
    """Every arm's beads of a :class:`ambots.deposit.Deposit` (world frame,
    m) in the bed frame, mm: (starts (K, 3), ends (K, 3), widths (K,),
    heights (K,)), the arms' beads together; the pieces of one extrusion
    joined (:func:`_join_pieces`)."""
    out = []
    for arm in deposit.arms:
        b = deposit.segments(arm)
        s, e = _bed_mm(b.starts, bed_pose), _bed_mm(b.ends, bed_pose)
        out.append(_join_pieces(s, e, b.area / b.height * 1e3, b.height * 1e3))
    if not out:
        z = np.zeros((0, 3))
        return z, z, np.zeros(0), np.zeros(0)
    return tuple(np.concatenate(x) for x in zip(*out))


def _line_intervals(polygons, c0, u, n2):
    """Parameter intervals [(t0, t1)] of the line c0 + t u inside the
    polygons (even-odd rule; ``n2`` the line's normal)."""
    ts = []
    for poly in polygons:
        P = np.asarray(poly, dtype=float).reshape(-1, 2)
        if len(P) < 3:
            continue
        Q = np.roll(P, -1, axis=0)
        da, db = (P - c0) @ n2, (Q - c0) @ n2
        cross = (da < 0) != (db < 0)
        s = da[cross] / (da[cross] - db[cross])
        X = P[cross] + s[:, None] * (Q[cross] - P[cross])
        ts.extend(((X - c0) @ u).tolist())
    ts = np.sort(ts)
    return list(zip(ts[0::2], ts[1::2]))


def seam_samples(model, planes, z_tops, heights, step_mm=0.2):
    """Sample points of every seam face: ``model`` (Manifold, mm), ``planes``
    {(a, b): (n, o)} the seam plane between parts a and b seen from a (n . p
    - o >= 0 on a's side; :func:`ambots.coordinate.zones.seam_planes`; ``o``
    per layer (L,) for a stepped seam).
    For each pair a < b (by name), the points of the plane inside the
    model's section at each layer's mid-height, every ``step_mm`` along the
    plane, where a and b are the parts meeting (on a's side of a's other
    seams, on b's side of b's).  Returns {(a, b): (points (M, 3), normal
    (3,))}."""
    out = {}
    names = sorted({a for a, _ in planes} | {b for _, b in planes})
    sections = [(z_tops[k] - heights[k] / 2.0, model.slice(float(z_tops[k] - heights[k] / 2.0)).to_polygons())
                for k in range(len(z_tops))]
    for a in names:
        for b in names:
            if not (a < b and (a, b) in planes and (b, a) in planes):
                continue
            n, o = planes[a, b]
            n2 = np.asarray(n, dtype=float)[:2]
            n2 = n2 / np.linalg.norm(n2)
            u = np.array([-n2[1], n2[0]])
            pts = []
            for k, (z, polys) in enumerate(sections):
                c0 = n2 * offset_at(o, k)
                for t0, t1 in _line_intervals(polys, c0, u, n2):
                    t = np.arange(t0 + step_mm / 2.0, t1, step_mm)
                    xy = c0 + t[:, None] * u
                    pts.append(np.column_stack([xy, np.full(len(t), z)]))
            P = np.concatenate(pts) if pts else np.zeros((0, 3))
            keep = np.ones(len(P), dtype=bool)
            for (x, y), (nn, oo) in planes.items():
                if (x in (a, b)) and y not in (a, b):
                    keep &= P @ np.asarray(nn, dtype=float) - np.min(oo) >= -1e-6
            out[a, b] = (P[keep], np.array([n2[0], n2[1], 0.0]))
    return out


def bonded_mask(points, normal, beads, margin_mm, chunk=2000):
    """(M,) bool: is each point of a seam face bonded, i.e. does one bead's
    box contain both ``points +- margin_mm * normal``?  ``beads``: (starts,
    ends, widths, heights) mm as :func:`deposit_beads_mm` gives them (the
    path is a box's top edge; its width across, horizontal)."""
    S, E, W, H = beads
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.zeros(len(P), dtype=bool)
    if not len(P) or not len(S):
        return out
    n2 = np.asarray(normal, dtype=float)[:2]
    d = E[:, :2] - S[:, :2]
    L = np.linalg.norm(d, axis=1)
    ok = L > 1e-9
    S, E, W, H, d, L = S[ok], E[ok], W[ok], H[ok], d[ok], L[ok]
    along = d / L[:, None]
    across = np.column_stack([-along[:, 1], along[:, 0]])
    ztop = np.maximum(S[:, 2], E[:, 2])
    zbot = np.minimum(S[:, 2], E[:, 2]) - H
    for z in np.unique(P[:, 2]):                  # one layer's points against that layer's beads
        rows = np.flatnonzero(P[:, 2] == z)
        k = np.flatnonzero((zbot <= z) & (ztop >= z))
        if not len(k):
            continue
        for i in range(0, len(rows), chunk):
            p = P[rows[i:i + chunk], :2]
            inside = np.ones((len(p), len(k)), dtype=bool)
            for sign in (1.0, -1.0):
                rel = (p + sign * margin_mm * n2)[:, None, :] - S[None, k, :2]
                a = np.einsum("mkj,kj->mk", rel, along[k])
                c = np.einsum("mkj,kj->mk", rel, across[k])
                inside &= (a >= 0) & (a <= L[None, k]) & (np.abs(c) <= W[None, k] / 2.0)
            out[rows[i:i + chunk]] = inside.any(axis=1)
    return out


def bonded_share(model, planes, deposit, bed_pose, z_tops, heights, bead_width, step_mm=0.2):
    """{"a/b": {"bonded_share": 0..1, "samples": M}} for every seam of
    ``planes`` ({(a, b): (n, o)}, :func:`ambots.coordinate.zones.seam_planes`)
    in ``deposit`` (world frame, m; the bed's pose ``bed_pose`` 4x4 maps the
    bed frame to it): points of the seam face (:func:`seam_samples`) bonded
    by one bead with a margin of a quarter ``bead_width`` (mm) on both sides
    (:func:`bonded_mask`)."""
    beads = deposit_beads_mm(deposit, bed_pose)
    out = {}
    for (a, b), (P, n) in seam_samples(model, planes, z_tops, heights, step_mm).items():
        if not len(P):
            continue
        # only the beads near the plane (a stepped seam's: near it on some layer) can straddle it
        o = P @ n
        near = (np.minimum(beads[0] @ n, beads[1] @ n) - o.max() <= bead_width) & \
               (np.maximum(beads[0] @ n, beads[1] @ n) - o.min() >= -bead_width)
        mask = bonded_mask(P, n, tuple(x[near] for x in beads), bead_width / 4.0)
        out["%s/%s" % (a, b)] = {"bonded_share": round(float(mask.mean()), 4), "samples": int(len(P))}
    return out


def seam_setup(parts, seam, settings, z_max_mm):
    """What a job's seam figures are measured against, as JSON (``job.json``'s
    ``seams``, so that the live capture measures its deposit as ``plan``
    does): the seam kind, the planes between the ``parts`` ({"a/b": {"normal",
    "offset_mm"}} seen from a), the slicer's layer tops and thicknesses up
    to ``z_max_mm`` (the model's top), the bead width and the lap band's
    reach (the interlock's depth plus a bead); a stepped seam's planes also
    carry ``layer_offsets_mm``, added to ``offset_mm`` on each layer
    (:mod:`ambots.seam_steps`).  None for fewer than two parts with work."""
    from ambots.coordinate.zones import seam_planes
    from ambots.slicer import layer_heights
    live = [p for p in parts if not p.empty]
    if len(live) < 2:
        return None
    z_tops, heights = layer_heights(float(z_max_mm), settings)
    planes = {"%s/%s" % k: {"normal": [round(float(x), 12) for x in n], "offset_mm": float(o)}
              for k, (n, o) in seam_planes(live).items()}
    for p in live:                       # a stepped seam: the offset added on each layer, seen from each side
        if getattr(p, "layer_offsets", None) is not None:
            for other in p.neighbours:
                if "%s/%s" % (p.arm.name, other) in planes:
                    planes["%s/%s" % (p.arm.name, other)]["layer_offsets_mm"] = [float(x) for x in p.layer_offsets]
    return {"seam": seam,
            "planes": planes,
            "z_tops_mm": [float(z) for z in z_tops], "heights_mm": [float(h) for h in heights],
            "bead_width_mm": float(settings.bead_width_mm),
            "reach_mm": float(interlock_depth_mm(settings.bead_width_mm, settings.layer_height_mm)
                              + settings.bead_width_mm)}


def beads_in_bed_mm(by_arm, bed_pose):
    """{arm: (p0, p1, t)} with p0, p1 (K, 3) in the world frame (m) -> the
    same in the bed frame (mm), as :func:`lap_order` takes them."""
    return {n: (_bed_mm(p0, bed_pose), _bed_mm(p1, bed_pose), np.asarray(t, dtype=float))
            for n, (p0, p1, t) in by_arm.items()}


def _bed_mm(P, bed_pose):
    """World points (K, 3), m -> the bed frame, mm."""
    T = np.linalg.inv(np.asarray(bed_pose, dtype=float))
    return (np.asarray(P, dtype=float) @ T[:3, :3].T + T[:3, 3]) * 1e3


def placed_model(job_dir, names):
    """The placed model again (Manifold, bed frame mm), from the parts a job
    folder holds (``<arm>.stl`` for the arms ``names``, written by
    :func:`ambots.job.write_job`): their union (an interlock's parts
    alternate across the seam; together they are the model)."""
    import os

    import trimesh

    from ambots.mesh import to_manifold
    model = None
    for n in names:
        m = to_manifold(trimesh.load(os.path.join(job_dir, n + ".stl"), force="mesh"))
        model = m if model is None else model + m
    return model


def seam_figures(setup, model, deposit, bed_pose, by_arm=None):
    """The seam figures of a deposit: ({"a/b": {"bonded_share", "samples"}},
    {"a/b": {"layers", "early"}}) by :func:`seam_setup`'s ``setup``;
    ``model`` the placed model (Manifold, bed frame mm), ``deposit`` (world
    m) and ``bed_pose`` as :func:`bonded_share` takes them, ``by_arm`` the
    beads with their times as :func:`lap_order` takes them (None: no lap
    order).  ({}, {}) without a setup."""
    if not setup:
        return {}, {}
    planes = {tuple(k.split("/")): (np.asarray(v["normal"], dtype=float),
                                    float(v["offset_mm"]) + np.asarray(v["layer_offsets_mm"], dtype=float)
                                    if v.get("layer_offsets_mm") else float(v["offset_mm"]))
              for k, v in setup["planes"].items()}
    z_tops = np.asarray(setup["z_tops_mm"], dtype=float)
    shares = bonded_share(model, planes, deposit, bed_pose, z_tops, np.asarray(setup["heights_mm"], dtype=float),
                          setup["bead_width_mm"])
    order = lap_order(by_arm, planes, setup["reach_mm"], z_tops) if by_arm is not None else {}
    return shares, order


def lap_order(by_arm, planes, reach_mm, z_tops):
    """Does each arm lay its beads of the lap band of layer n (within
    ``reach_mm`` of a seam plane, e.g. d + a bead width) only after its
    neighbour has laid its beads of that band in layer n - 1?  With an
    interlock the band of one arm's layer n rests on the other arm's layer
    n - 1.  ``by_arm``: {arm: (p0 (K, 3), p1 (K, 3) bed frame mm, t (K,) s
    when laid)}; ``planes`` as :func:`seam_samples` takes them; ``z_tops``
    the slicer's layer tops (mm).  Returns {"a/b": {"layers": checked
    (arm, layer) pairs, "early": how many of them started before the
    neighbour's layer below was done}}."""
    z_tops = np.asarray(z_tops, dtype=float)
    out = {}
    names = sorted(by_arm)
    for a in names:
        for b in names:
            if not (a < b and (a, b) in planes and (b, a) in planes):
                continue
            n, o = planes[a, b]
            n = np.asarray(n, dtype=float)
            first, last = {}, {}
            for arm in (a, b):
                p0, p1, t = (np.asarray(x, dtype=float) for x in by_arm[arm])
                if not len(t):
                    continue
                # the slicer's layer k holds z in (top k-1, top k]: a support layer laid low under an
                # overhang (its z gap) is still its layer, not the one below
                layer = np.minimum(np.searchsorted(z_tops, p1[:, 2] - 1e-3), len(z_tops) - 1)
                ok = o if np.ndim(o) == 0 else np.asarray(o, dtype=float)[np.minimum(layer, len(o) - 1)]
                s0, s1 = p0 @ n - ok, p1 @ n - ok
                near = (np.minimum(s0, s1) <= reach_mm) & (np.maximum(s0, s1) >= -reach_mm)
                mid = (p0 + p1) / 2.0
                for (x, y), (nn, oo) in planes.items():      # at this seam, not where the plane runs elsewhere
                    if x == arm and y not in (a, b):
                        near &= mid @ np.asarray(nn, dtype=float) - np.min(oo) >= -reach_mm
                for k in np.unique(layer[near]):
                    sel = near & (layer == k)
                    first[arm, k], last[arm, k] = float(t[sel].min()), float(t[sel].max())
            checked = early = 0
            for (arm, k), t0 in first.items():
                other = b if arm == a else a
                if (other, k - 1) in last:
                    checked += 1
                    early += t0 < last[other, k - 1]
            out["%s/%s" % (a, b)] = {"layers": checked, "early": early}
    return out
