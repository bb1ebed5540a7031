"""Capsule collision model of the arms: clearance between two arms, to the
print bed and to the part printed so far.

Every link of our arm models carries cylinders (and spheres) as both visual
and collision geometry (``urdf/common.xacro``): the model's own link
cylinders, the arm profile's ``bodies:`` (joint housings and link tubes of
the real arm's size, :class:`ambots.config.Capsule`) and, on the ``nozzle``
link, the print head (``tool.head:``), so RViz shows what is checked.  Each
collision cylinder becomes a *capsule*: a segment on the cylinder's axis
plus its radius.  The segment's endpoints are inset by
``min(radius, length / 2)`` from the flat ends, so the capsule never reaches
past them; it bulges out sideways only where the rounded caps meet the rim,
i.e. it lies inside the cylinder except for a cylinder shorter than its
diameter, which becomes a ball of its radius.  A profile body (a capsule) is
drawn as the cylinder of length ``|b - a| + 2 r`` around its segment, so it
comes back exactly.  A sphere is a capsule of zero length.  A capsule lying
wholly inside another of the same link (a model cylinder inside the
profile's envelope) is dropped: it never decides a clearance.  The head's
bodies stop 5 mm short of the tip (the profiles; at least
:data:`ambots.config.HEAD_TIP_GAP`), so a nozzle printing on the part is no
contact.

API (metres, radians; N configurations, C capsules of one arm):

* :class:`ArmBody` -- ``ArmBody.from_arm(arm)`` (an
  :class:`~ambots.config.ArmInstance`, or a bare profile standing at the
  world origin); ``body.capsules(Q)`` -> ``(A, B, radii)``: endpoints
  (N, C, 3) in the world frame for joint vectors ``Q`` (N, n); attributes
  ``names`` (C,) link names (without the arm prefix), ``radii`` (C,),
  ``link_index`` (C,) index of each capsule's frame in
  :meth:`~ambots.kinematics.ArmKinematics.link_frames`.
* :func:`segment_distance` -- closest distance between segments, broadcast.
* :func:`capsule_distances` -- (N, C1, C2) surface distances of two capsule sets.
* :func:`clearance_between` -- (N,) clearance of two arms at N simultaneous
  configurations.
* :func:`box_clearance` -- (N,) clearance of capsules to an axis-aligned box.
* :func:`bed_clearance` -- (N,) clearance of an arm to the bed slab.
* :func:`part_clearance` -- (N,) clearance of an arm to the part printed so far
  (a world axis-aligned box, e.g. :meth:`ambots.deposit.Deposit.bounds`).
* :func:`seam_zone` / :func:`seam_zone_mm` -- the seam-zone width of the
  concurrent schedule (:mod:`ambots.coordinate`) from the arms' geometry;
  :func:`seam_zones_mm` -- the same width pair by pair (facing protrusions
  only, no clearance check), for cells of many arms.

A *clearance* is a surface-to-surface distance: positive apart, zero touching,
negative overlapping (minus the depth of the deepest segment point inside the
other body, minus the radius).  Self-collision is not modelled.
"""
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Dict, NamedTuple, Tuple

import numpy as np

from ambots.config import ArmInstance, pose_matrix
from ambots.errors import KinematicsError, UnreachableError

__all__ = ["ArmBody", "segment_distance", "capsule_distances", "clearance_between", "box_clearance", "box_clear",
           "bed_box", "BED_SKIP",
           "bed_clearance", "part_clearance", "SeamZone", "seam_zone", "seam_zone_mm", "seam_zones_mm",
           "CollisionCheck"]

#: capsule pairs evaluated at once by :func:`capsule_distances` (bounds memory)
_CHUNK_PAIRS = 1 << 18
#: golden-section iterations of :func:`box_clearance`: 0.618**45 < 5e-10
_GOLDEN_ITERS = 45


# --------------------------------------------------------------- helpers
def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def _cross(a, b):
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _transform(T, X):
    """Apply a 4x4 transform ``T`` to points ``X`` (..., 3)."""
    return X @ T[:3, :3].T + T[:3, 3]


def _floats(text, n, what):
    try:
        v = [float(x) for x in (text or "").split()] if text is not None else [0.0] * n
    except ValueError:
        v = []
    if len(v) != n or not np.all(np.isfinite(v)):
        raise KinematicsError("%s: expected %d finite numbers, got %r" % (what, n, text))
    return v


# ------------------------------------------------------------ arm model
def _collision_capsule(link, col):
    """(a, b, radius) in the link frame of one <collision> element."""
    where = "link %r collision" % link
    geom = col.find("geometry")
    shape = geom[0] if geom is not None and len(geom) else None
    if shape is None or shape.tag not in ("cylinder", "sphere"):
        raise KinematicsError("%s: %s geometry is not supported (cylinders and spheres only)"
                              % (where, "no" if shape is None else shape.tag))
    r = _floats(shape.get("radius"), 1, where + " radius")[0]
    length = _floats(shape.get("length"), 1, where + " length")[0] if shape.tag == "cylinder" else 0.0
    if r <= 0 or length < 0:
        raise KinematicsError("%s: radius must be > 0 and length >= 0, got %g, %g" % (where, r, length))
    origin = col.find("origin")
    xyz = _floats(None if origin is None else origin.get("xyz"), 3, where + " origin xyz")
    rpy = _floats(None if origin is None else origin.get("rpy"), 3, where + " origin rpy")
    T = pose_matrix(xyz, rpy)
    half = length / 2 - min(r, length / 2)
    return T[:3, 3] - half * T[:3, 2], T[:3, 3] + half * T[:3, 2], r


def _parse_capsules(urdf_xml, chain):
    """Capsules of every collision element of a URDF whose links all belong
    to ``chain``: (names, link_index, a_local, b_local, radii)."""
    try:
        root = ET.fromstring(urdf_xml.encode() if isinstance(urdf_xml, str) else urdf_xml)
    except ET.ParseError as exc:
        raise KinematicsError("malformed URDF: %s" % exc) from None
    index = {chain.base: 0}
    index.update({s.link: i + 1 for i, s in enumerate(chain.segments)})
    names, idx, a, b, r = [], [], [], [], []
    for link in root.findall("link"):
        name = link.get("name")
        for col in link.findall("collision"):
            if name not in index:
                raise KinematicsError("link %r has collision geometry but is not on the chain %s -> %s"
                                      % (name, chain.base, chain.tip))
            ca, cb, cr = _collision_capsule(name, col)
            names.append(name)
            idx.append(index[name])
            a.append(ca)
            b.append(cb)
            r.append(cr)
    if not names:
        raise KinematicsError("the URDF has no collision geometry on the chain %s -> %s" % (chain.base, chain.tip))
    names, idx, a, b, r = np.array(names), np.array(idx), np.array(a), np.array(b), np.array(r)
    keep = ~_inside_another(idx, a, b, r)
    return names[keep], idx[keep], a[keep], b[keep], r[keep]


def _inside_another(idx, a, b, r):
    """Bool (C,): capsules (segments a-b, radii r, frames idx) lying wholly
    inside another capsule of the same link: both segment ends within the
    other's radius less their own (the distance to a segment is convex along
    a segment, so every point of the capsule is then inside).  Of identical
    capsules the first is kept.  Such a capsule never decides a clearance."""
    d = b - a
    ends = [_point_segment(p[:, None], a[None], d[None], _dot(d, d)[None]) for p in (a, b)]   # (C, C) each
    within = (idx[:, None] == idx[None, :]) & (np.maximum(*ends) + r[:, None] <= r[None, :] + 1e-12)
    np.fill_diagonal(within, False)
    first = np.arange(len(r))[:, None] < np.arange(len(r))[None, :]
    within &= ~(within.T & first)             # of two identical capsules, the first stays
    return within.any(axis=1)


class ArmBody:
    """The capsules of one arm.

    Parameters
    ----------
    kin : :class:`~ambots.kinematics.ArmKinematics` built from ``urdf_xml``
    urdf_xml : the arm's URDF (string); every link with collision geometry
        must be on ``kin``'s chain
    base_pose : (4, 4) pose of the chain's base link in the world frame
    name : the arm's instance name (for messages)
    """

    def __init__(self, kin, urdf_xml, base_pose=None, name=""):
        self.kin = kin
        self.name = name
        self.base_pose = np.eye(4) if base_pose is None else np.asarray(base_pose, dtype=float)
        self.names, self.link_index, self._a, self._b, self.radii = _parse_capsules(urdf_xml, kin.chain)

    @classmethod
    def from_arm(cls, arm):
        """From an :class:`~ambots.config.ArmInstance` (placed at its base pose)
        or a bare :class:`~ambots.config.ArmProfile` (base at the world origin)."""
        from ambots.kinematics import ArmKinematics
        from ambots.model import arm_urdf
        instance = isinstance(arm, ArmInstance)
        profile = arm.profile if instance else arm
        urdf = arm_urdf(profile)
        kin = ArmKinematics.from_urdf(urdf, base=profile.base_link, tip=profile.tool_link, trail=profile.tool_trail)
        return cls(kin, urdf, arm.base_pose if instance else None, arm.name)

    def __len__(self):
        return len(self.names)

    def mask(self, skip=()):
        """Bool (C,): capsules whose link is not in ``skip`` (link names without
        prefix; an unknown name raises ``ValueError``)."""
        unknown = set(skip) - set(self.names)
        if unknown:
            raise ValueError("arm %r has no capsule on link(s) %s (links: %s)"
                             % (self.name, ", ".join(sorted(unknown)), ", ".join(self.names)))
        return ~np.isin(self.names, list(skip))

    def capsules(self, Q):
        """Capsules at joint vectors ``Q`` (N, n) or (n,): ``(A, B, radii)`` with
        endpoints A, B (N, C, 3) in the world frame, m, and radii (C,), m."""
        F = self.kin.link_frames(np.atleast_2d(np.asarray(Q, dtype=float)))[:, self.link_index]
        F = self.base_pose @ F                                        # (N, C, 4, 4)
        R, t = F[..., :3, :3], F[..., :3, 3]
        A = np.einsum("ncij,cj->nci", R, self._a) + t
        B = np.einsum("ncij,cj->nci", R, self._b) + t
        return A, B, self.radii


# ----------------------------------------------------------- distances
def _point_segment(p, q0, d, dd):
    """Distance from points p to segments q0 + t d, t in [0, 1]; dd = d.d."""
    w = p - q0
    t = np.clip(np.where(dd > 0, _dot(w, d) / np.where(dd > 0, dd, 1.0), 0.0), 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * d, axis=-1)


def segment_distance(P0, P1, Q0, Q1):
    """Closest distance between segments P0-P1 and Q0-Q1.

    Arguments are (..., 3) arrays that broadcast together; returns the
    broadcast shape without the last axis, m.  Degenerate (point) segments
    and parallel segments are handled: the result is the minimum over the
    clamped closest-point pair of the two lines (Ericson's algorithm, with
    the normal computed by a cross product, so it stays accurate at small
    angles) and the four endpoint-to-segment distances.  Every candidate is
    a distance between two actual points of the segments, so the result is
    never below the true distance, and the boundary candidates make it exact
    when the optimum lies on an endpoint (always the case for parallel
    segments).
    """
    P0, P1, Q0, Q1 = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (P0, P1, Q0, Q1)))
    d1, d2, r = P1 - P0, Q1 - Q0, P0 - Q0
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    c, f = _dot(d1, r), _dot(d2, r)
    n = _cross(d1, d2)
    denom = _dot(n, n)
    skew = denom > 1e-24 * a * e
    s = np.where(skew, _dot(n, _cross(d2, r)) / np.where(skew, denom, 1.0), 0.0).clip(0.0, 1.0)
    t_free = np.where(e > 0, (b * s + f) / np.where(e > 0, e, 1.0), 0.0)
    t = t_free.clip(0.0, 1.0)
    s = np.where(t != t_free, np.where(a > 0, (b * t - c) / np.where(a > 0, a, 1.0), 0.0).clip(0.0, 1.0), s)
    best = np.linalg.norm(r + s[..., None] * d1 - t[..., None] * d2, axis=-1)
    for p, q0, d, dd in ((P0, Q0, d2, e), (P1, Q0, d2, e), (Q0, P0, d1, a), (Q1, P0, d1, a)):
        best = np.minimum(best, _point_segment(p, q0, d, dd))
    return best


def capsule_distances(A1, B1, r1, A2, B2, r2):
    """Surface distances between every capsule of one set and every capsule
    of another, configuration by configuration.

    A1, B1 : (N, C1, 3) and A2, B2 : (N, C2, 3) endpoints, m; r1 (C1,),
    r2 (C2,) radii, m.  Returns (N, C1, C2), m (negative = overlap).
    Evaluated in chunks of configurations to bound memory.
    """
    N, C1, C2 = A1.shape[0], A1.shape[1], A2.shape[1]
    out = np.empty((N, C1, C2))
    step = max(1, _CHUNK_PAIRS // max(1, C1 * C2))
    for i in range(0, N, step):
        j = slice(i, i + step)
        out[j] = segment_distance(A1[j, :, None], B1[j, :, None], A2[j, None], B2[j, None])
    return out - np.asarray(r1)[:, None] - np.asarray(r2)[None, :]


def clearance_between(body_a, QA, body_b, QB):
    """Clearance (N,), m, between two arms whose joint vectors are ``QA``
    (N, na) and ``QB`` (N, nb), taken together row by row: the minimum
    surface distance over every capsule pair (negative = penetration)."""
    A1, B1, r1 = body_a.capsules(QA)
    A2, B2, r2 = body_b.capsules(QB)
    if A1.shape[0] != A2.shape[0]:
        raise ValueError("QA and QB must hold the same number of configurations, got %d and %d"
                         % (A1.shape[0], A2.shape[0]))
    return capsule_distances(A1, B1, r1, A2, B2, r2).min(axis=(1, 2))


def _box_sdf(X, lo, hi):
    """Signed distance of points X (..., 3) to boxes [lo, hi] (negative inside)."""
    d = np.maximum(lo - X, X - hi)
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0)


def box_clearance(A, B, radii, box_min, box_max, mask=None):
    """Clearance (N,), m, of capsules to an axis-aligned box.

    A, B : (N, C, 3) capsule endpoints, m;  radii : (C,), m
    box_min, box_max : (3,) or (N, 3) box corners in the same frame, m
    mask : optional (C,) bool, capsules to consider (default all)

    Each capsule's clearance is min over its segment of the box's signed
    distance, minus its radius: negative when the capsule overlaps the box
    (then minus the depth of its deepest segment point, minus the radius).
    The signed distance of a box is convex, so along a segment it is a convex
    function of the segment parameter, minimised by golden-section search
    (45 steps: parameter bracket < 5e-10) and compared with both endpoints.
    The value returned is that of an actual segment point, so it is never
    below the true clearance and exceeds it by at most 5e-10 x the segment
    length (under a nanometre for our links).
    """
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    lo, hi = np.asarray(box_min, dtype=float), np.asarray(box_max, dtype=float)
    if np.any(lo > hi):
        raise ValueError("box_min must be <= box_max in every axis, got %s and %s" % (lo, hi))
    if lo.ndim == 2:
        lo, hi = lo[:, None, :], hi[:, None, :]
    radii = np.asarray(radii, dtype=float)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if not mask.any():
            raise ValueError("no capsule left to check (every link skipped)")
        A, B, radii = A[:, mask], B[:, mask], radii[mask]
    D = B - A
    # Only capsules that may hold the row's minimum are searched: the box's
    # signed distance is 1-Lipschitz, so a capsule's clearance is at least the
    # value at its midpoint minus half its length, and at most the value at
    # either end; a capsule whose lower bound exceeds the row's smallest upper
    # bound cannot be the closest.
    ends = np.minimum(_box_sdf(A, lo, hi), _box_sdf(B, lo, hi)) - radii         # (N, C)
    lower = _box_sdf(A + D / 2, lo, hi) - np.linalg.norm(D, axis=-1) / 2 - radii
    rows, caps = np.nonzero(lower < ends.min(axis=1, keepdims=True))
    if lo.ndim == 3:
        lo, hi = lo[rows, 0], hi[rows, 0]
    A, D = A[rows, caps], D[rows, caps]

    def f(t):
        return _box_sdf(A + t[..., None] * D, lo, hi)

    g = (np.sqrt(5.0) - 1.0) / 2.0
    left, right = np.zeros(len(rows)), np.ones(len(rows))
    x1, x2 = right - g, left + g
    f1, f2 = f(x1), f(x2)
    for _ in range(_GOLDEN_ITERS):
        keep_left = f1 <= f2                      # the minimum lies in [left, x2]
        right = np.where(keep_left, x2, right)
        left = np.where(keep_left, left, x1)
        x_new = np.where(keep_left, right - g * (right - left), left + g * (right - left))
        f_new = f(x_new)
        x1, f1, x2, f2 = (np.where(keep_left, x_new, x2), np.where(keep_left, f_new, f2),
                          np.where(keep_left, x1, x_new), np.where(keep_left, f1, f_new))
    ends[rows, caps] = np.minimum(ends[rows, caps], np.minimum(f1, f2) - radii[caps])
    return ends.min(axis=1)


def box_clear(A, B, radii, box_min, box_max, margin, mask=None):
    """Whether each row's capsules keep ``margin`` (m) from the box: bool
    (N,), the same answer as ``box_clearance(...) >= margin``, first from a
    bound and searched (:func:`box_clearance`) only in the rows it leaves
    open.  The bound: along a segment the box's signed distance is at
    least, on every axis, the larger of the two ends' smaller distances
    out of the box's face below and above."""
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    radii = np.asarray(radii, dtype=float)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        A, B, radii = A[:, mask], B[:, mask], radii[mask]
    lo, hi = np.asarray(box_min, dtype=float), np.asarray(box_max, dtype=float)
    below = np.minimum(lo - A, lo - B)                   # (N, C, 3)
    above = np.minimum(A - hi, B - hi)
    bound = np.maximum(below, above).max(axis=-1) - radii
    ok = (bound >= margin).all(axis=1)
    rows = np.flatnonzero(~ok)
    if len(rows):
        ok[rows] = box_clearance(A[rows], B[rows], radii, lo, hi) >= margin
    return ok


#: links the bed check leaves out: those mounted at or below the table
BED_SKIP = ("base_link",)


def bed_clearance(body, Q, cell, skip=BED_SKIP):
    """Clearance (N,), m, of an arm at joint vectors ``Q`` (N, n) to the print
    bed: the slab ``cell.bed.size`` (x, y, thickness) below the bed's top
    surface.  ``skip``: links not checked (those mounted at or below the
    table, like the base link; names without the arm prefix)."""
    A, B, r = body.capsules(Q)
    inv = np.linalg.inv(cell.bed.pose)
    return box_clearance(_transform(inv, A), _transform(inv, B), r, *bed_box(cell), body.mask(skip))


def bed_box(cell):
    """The bed's slab in its own frame (its top at z = 0): (lo, hi), m."""
    sx, sy, thick = cell.bed.size
    return (-sx / 2, -sy / 2, -thick), (sx / 2, sy / 2, 0.0)


def part_clearance(body, Q, box_min, box_max, skip=()):
    """Clearance (N,), m, of an arm at joint vectors ``Q`` (N, n) to the part
    printed so far, approximated by the world axis-aligned box ``box_min`` ..
    ``box_max`` ((3,) or (N, 3), m; e.g. :meth:`ambots.deposit.Deposit.bounds`).
    The nozzle link is checked too: the head's bodies stop 5 mm short of the
    tip (the profiles' ``tool.head``), so a nozzle printing on the part's top
    face has about +5 mm clearance there.
    ``skip``: link names not checked."""
    A, B, r = body.capsules(Q)
    return box_clearance(A, B, r, box_min, box_max, body.mask(skip))


# ------------------------------------------------------------ seam zone
@dataclass(frozen=True)
class SeamZone:
    """Seam-zone widths of the concurrent schedule, from the arms' geometry (mm).

    ``any_mm``: the sum of two neighbours' protrusions in the worst horizontal
    direction, plus the margin.  ``facing_mm``: the same with protrusions
    measured only along the seam normal, towards the neighbour's base.
    ``protrusion_any_mm[arm]`` and ``protrusion_facing_mm[(arm, neighbour)]``
    are the parts.  ``clearance_any_mm`` / ``clearance_facing_mm``: the
    smallest arm-to-arm clearance (all capsules, no height band) found over
    pairs of sampled configurations at the same height whose nozzles are at
    least that zone width apart along the seam normal (NaN: no such pair).

    ``any_mm`` counts each arm's own forearm, shoulder and base trailing back
    towards its base (they are within the band of a nozzle on the bed), so it
    is about the arms' reach, not a usable zone; ``facing_mm`` is the one to
    use.  Default cell, 10 mm margin: facing 50.0 mm (20 mm each, the fan
    ducts of the print heads on their brackets; 154.3 mm with the heads on
    the flanges' axes, before session 14: the wrists, Kinova 68.3, UR10
    76.0), any direction 2021 mm."""
    any_mm: float
    facing_mm: float
    margin_mm: float
    band: float
    protrusion_any_mm: Dict[str, float]
    protrusion_facing_mm: Dict[Tuple[str, str], float]
    clearance_any_mm: float
    clearance_facing_mm: float


class _Sampled(NamedTuple):
    """One arm's sampled nozzle-down configurations: tips (M, 3) and capsule
    endpoints (M, C, 3) in the bed frame, joint vectors Q (M, n)."""
    arm: object
    body: ArmBody
    tips: np.ndarray
    Q: np.ndarray
    A: np.ndarray
    B: np.ndarray


def _solve_down(cell, arm, body, tips):
    """IK from the arm's home for nozzle-down tips (M, 3) in the bed frame:
    (Q (M, n), ok (M,))."""
    from ambots.workspace import down_in_base, world_to_base
    pts = _transform(cell.bed.pose, tips)
    Q, ok, _ = body.kin.ik_batch(world_to_base(arm, pts), np.asarray(arm.profile.home), down_in_base(arm))
    return Q, ok


def _sample(cell, arm, n, heights):
    """IK at an n x n bed grid at every height; unreachable points left out."""
    from ambots.workspace import bed_points
    body = ArmBody.from_arm(arm)
    tips = _transform(np.linalg.inv(cell.bed.pose), bed_points(cell, n, heights))
    Q, ok = _solve_down(cell, arm, body, tips)
    return _solved(cell, arm, body, tips, Q, ok, "bed grid points")


def _solved(cell, arm, body, tips, Q, ok, what):
    """:class:`_Sampled` of the poses solved (``ok``) among ``Q`` for the
    nozzle-down ``tips`` (bed frame, m); :class:`UnreachableError` naming the
    arm and how many ``what`` it tried if none was."""
    if not ok.any():
        raise UnreachableError("arm %r reaches none of the %d %s with the nozzle down" % (arm.name, len(tips), what))
    A, B, _ = body.capsules(Q[ok])
    inv = np.linalg.inv(cell.bed.pose)
    return _Sampled(arm, body, tips[ok], Q[ok], _transform(inv, A), _transform(inv, B))


def _protrusion(s, band, u=None):
    """Horizontal protrusion (M,), m, of the capsules of sampled
    configurations ``s`` from the vertical nozzle axis through each tip:
    over capsule points whose segment point lies at most ``band + r`` above
    the tip (conservative: the full radius r is counted up to there), the
    largest offset along the horizontal unit vector ``u`` (2,) of the bed
    frame, or the largest horizontal distance when ``u`` is None."""
    A, B, r, tips = s.A, s.B, s.body.radii, s.tips
    top = (tips[:, 2] + band)[:, None] + r                          # (M, C)
    za, zb = A[..., 2], B[..., 2]
    t_cross = ((top - za) / np.where(zb != za, zb - za, 1.0))[..., None]
    cross = A + t_cross * (B - A)
    ends = [np.where((za > top)[..., None], cross, A), np.where((zb > top)[..., None], cross, B)]
    off = []
    for P in ends:
        h = P[..., :2] - tips[:, None, :2]
        off.append(np.linalg.norm(h, axis=-1) if u is None else h @ u)
    below = (za <= top) | (zb <= top)
    return np.where(below, np.maximum(off[0], off[1]) + r, -np.inf).max(axis=1)


def _shifted_clearance(cell, sa, sb, u, z):
    """Clearance (m) of arm b placed (IK) with its nozzle exactly ``z`` along
    ``u`` from each of arm a's sampled tips, on the bed; inf if none fits."""
    sx, sy, _ = cell.bed.size
    tips = sa.tips + z * np.append(u, 0.0)
    on_bed = (np.abs(tips[:, 0]) <= sx / 2 + 1e-9) & (np.abs(tips[:, 1]) <= sy / 2 + 1e-9)
    Qb, ok = _solve_down(cell, sb.arm, sb.body, tips[on_bed])
    if not ok.any():
        return np.inf
    return float(clearance_between(sa.body, sa.Q[on_bed][ok], sb.body, Qb[ok]).min())


def _pair_clearance(cell, sa, sb, u, z):
    """Smallest clearance (m, inf if no pair) between arms a and b with their
    nozzles at the same height and at least ``z`` apart along ``u`` (a's side
    to b's side): every such pair of sampled configurations, plus each arm's
    samples with the other arm solved exactly ``z`` away."""
    ia, ib = np.nonzero(np.isclose(sa.tips[:, None, 2], sb.tips[None, :, 2], atol=1e-9))
    far = (sb.tips[ib, :2] - sa.tips[ia, :2]) @ u >= z
    grid = (float(clearance_between(sa.body, sa.Q[ia[far]], sb.body, sb.Q[ib[far]]).min())
            if far.any() else np.inf)
    return min(grid, _shifted_clearance(cell, sa, sb, u, z), _shifted_clearance(cell, sb, sa, -u, z))


def seam_zone(cell, arms=None, margin_mm=10.0, band=0.35, n=9, n_heights=4):
    """Seam-zone width for arms printing concurrently (see :mod:`ambots.coordinate`).

    Every pair of ``arms`` (default: the cell's) is treated as sharing a seam,
    a vertical plane perpendicular to the line between their bases (as in
    :mod:`ambots.partition`).  Each arm's nozzle-down configurations are
    solved (IK seeded from its home) at an ``n`` x ``n`` bed grid at
    ``n_heights`` heights from 0 to ``bed.max_height``; unreachable points are
    left out.  An arm's protrusion is the largest horizontal distance (bed xy
    plane) from the nozzle axis of its capsules below the nozzle + ``band``
    (m), over all its configurations: in any direction, or along the seam
    normal towards the neighbour.  Zone = protrusion A + protrusion B +
    ``margin_mm``, maximised over the pairs.  Each zone is then checked with
    :func:`clearance_between` (all capsules, no band).  Returns a
    :class:`SeamZone`.
    """
    from ambots.partition import arm_sites_mm
    arms = list(cell.arms if arms is None else arms)
    if len(arms) < 2:
        raise ValueError("a seam needs at least two arms")
    heights = np.linspace(0.0, cell.bed.max_height, n_heights)
    sites = arm_sites_mm(cell, arms) / 1000.0
    sampled = [_sample(cell, arm, n, heights) for arm in arms]
    p_any = {s.arm.name: float(_protrusion(s, band).max()) for s in sampled}
    margin = margin_mm / 1000.0
    p_face, z_any, z_face = {}, 0.0, 0.0
    pairs = []
    for i, sa in enumerate(sampled):
        for j in range(i + 1, len(sampled)):
            sb = sampled[j]
            u = (sites[j] - sites[i]) / np.linalg.norm(sites[j] - sites[i])     # from a towards b
            a, b = sa.arm.name, sb.arm.name
            p_face[a, b] = float(_protrusion(sa, band, u).max())
            p_face[b, a] = float(_protrusion(sb, band, -u).max())
            z_any = max(z_any, p_any[a] + p_any[b] + margin)
            z_face = max(z_face, p_face[a, b] + p_face[b, a] + margin)
            pairs.append((sa, sb, u))
    c_any = min(_pair_clearance(cell, sa, sb, u, z_any) for sa, sb, u in pairs)
    c_face = min(_pair_clearance(cell, sa, sb, u, z_face) for sa, sb, u in pairs)
    mm = lambda v: float(v) * 1000.0 if np.isfinite(v) else float("nan")  # noqa: E731
    return SeamZone(mm(z_any), mm(z_face), float(margin_mm), float(band),
                    {k: mm(v) for k, v in p_any.items()}, {k: mm(v) for k, v in p_face.items()},
                    mm(c_any), mm(c_face))


def seam_zone_mm(cell, arms=None, margin_mm=10.0, direction="facing", **kw):
    """Seam-zone width (mm) from :func:`seam_zone`: ``direction`` ``"facing"``
    (protrusions along the seam normal, towards the neighbour) or ``"any"``
    (worst horizontal direction).  ``kw``: ``band``, ``n``, ``n_heights``."""
    if direction not in ("facing", "any"):
        raise ValueError("direction must be 'facing' or 'any', got %r" % (direction,))
    z = seam_zone(cell, arms, margin_mm, **kw)
    width = z.facing_mm if direction == "facing" else z.any_mm
    # rounded up to 0.01 mm: the sweep's last bits vary with how the BLAS
    # threads split its sums (1e-13 mm between two runs on a loaded
    # machine), and the seam bands cut segments at multiples of this width,
    # so the same job must get the very same width every time
    return math.ceil(width * 100.0 - 1e-6) / 100.0


def seam_zones_mm(cell, arms=None, pairs=None, margin_mm=10.0, band=0.35, n=9, n_heights=4, spacing=0.05,
                  window=0.5, parts=None, part_spacing=0.01, clearance=None):
    """Seam-zone width (mm) of each pair of arms: the facing protrusions of
    the two arms across the plane between their shares (the line between
    their bases for two arms) plus ``margin_mm``, as :func:`seam_zone`
    computes them (``facing_mm`` is the largest of these), without its
    clearance check, so a cell of many arms costs one IK sampling per arm.

    Each arm is sampled (IK from its home, nozzle down) on a bed grid of at
    least ``n`` x ``n`` points, at most ``spacing`` (m) apart, at
    ``n_heights`` heights; a redundant arm (more than 6 joints) also from
    seeds with its upper-arm roll turned by up to 0.8 rad, since along its
    self-motion its joints depend on the path it printed.  Only the samples whose nozzle is
    on the arm's own share of the bed count (the part it would get if the
    whole bed were split among ``arms`` like a model,
    :func:`ambots.partition.partition`: an arm never prints on another's
    share, and on a long bed it could reach far past its neighbour in odd
    poses); for a pair, of those only the ones at most ``window`` (m) from
    the other arm's share (an arm far from a seam is not at it), and with
    the nozzle no farther from the plane between them than the arm's own
    base (farther, the fixed base stays between the nozzle and the plane).
    Two arms never that near each other (far apart in a row) get a zone of
    ``margin_mm``.  For the default cell this gives the same 50.0 mm as
    :func:`seam_zone`'s ``facing_mm``.

    ``parts``: the :class:`~ambots.partition.Part` of each arm of a job
    (mm): the shares are then the parts themselves (a grid ``part_spacing``
    (m) apart over each part's bounding box, inside its planes, from the
    bed to the part's top), so that the zone fits the poses the job uses.
    ``pairs``: the (name, name) pairs wanted (default: every pair of
    ``arms``).  Returns {(a, b): mm}, with both orders of every pair.

    ``clearance``: a dict to fill, for the pairs with a seam plane from both
    sides that do not face each other along it (:func:`_at_an_angle`), with
    the zone from the clearance of the sampled poses themselves (all
    capsules): the smallest sum of distances across the seam beyond which
    every sampled pair keeps ``margin_mm``, plus one grid step
    (:func:`_clearance_zone`), at most the protrusions' zone.  The
    protrusions, projected on the normal, are tight for arms that face each
    other along it (the default cell's) and loose for arms at an angle to
    it, which count each arm's wrist and forearm reaching along the normal
    although the two never meet there: arms beside each other along a beam
    (until session 21 the only pairs that got this zone), four in the
    corners of a bed (the Kinova and the UR10 on the 300 mm plate: 73.7 mm
    projected, 59.5 mm by clearance).  Facing arms keep the projection: on
    parts narrower than the zone (a 20 mm tower) no sampled pair is far
    enough apart to tell, and the clearance would only say how far apart
    they can get."""
    from ambots.partition import arm_sites_mm
    arms = list(cell.arms if arms is None else arms)
    names = [a.name for a in arms]
    if pairs is None:
        pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    pairs = [(a, b) for a, b in pairs if a != b]
    if not pairs:
        return {}
    if parts is None:
        grid = _bed_shares(cell, arms, n, spacing)
    else:
        grid = _part_shares(names, parts, part_spacing)
    tips, owner = _share_tips(grid, n_heights)
    used = sorted({x for pair in pairs for x in pair}, key=names.index)
    # poses on each arm's own share only
    sampled = {name: _sample_share(cell, arms[names.index(name)], tips[owner == names.index(name)]) for name in used}
    sites = dict(zip(names, arm_sites_mm(cell, arms) / 1000.0))
    plane_of = _planes_between(grid.regions, names)
    out = {}
    for a, b in pairs:
        ia, ib = names.index(a), names.index(b)
        near = []
        for x, ix, other in ((a, ia, ib), (b, ib, ia)):
            protrusion, mine, d = _facing_side(sampled[x], grid, plane_of.get((ix, other)), sites[x],
                                               sites[names[other]], other, band)
            near.append((protrusion, mine & (d <= window)))
        z = margin_mm + sum(float(p[k].max()) * 1000.0 if k.any() else 0.0 for p, k in near)
        out[a, b] = out[b, a] = z
        if clearance is not None and (ia, ib) in plane_of and (ib, ia) in plane_of \
                and _at_an_angle(plane_of[ia, ib][0], sites[a], sites[b],
                                 [sampled[x].tips[k, :2] for x, (_, k) in zip((a, b), near)]):
            sel = []
            for (x, ix, other), (_, k) in zip(((a, ia, ib), (b, ib, ia)), near):
                nx, ox = plane_of[ix, other]
                dist = sampled[x].tips[:, :2] * 1000.0 @ nx - ox
                sel.append((sampled[x], np.nonzero(k & (dist < z))[0], dist))
            zc = _clearance_zone(sel[0], sel[1], z, margin_mm, grid.step_mm)
            clearance[a, b] = clearance[b, a] = min(z, zc)
    return out


class _Shares(NamedTuple):
    """The arms' shares for :func:`seam_zones_mm`: grid points ``flat``
    (K, 2) m in the bed frame, ``flat_owner`` (K,) the index of the arm
    whose share holds each (-1: none), the grid step (mm) and per arm its
    ``regions`` entry (its planes (normal, offset mm), the share's top (m),
    the arms on the other side of its planes)."""
    flat: np.ndarray
    flat_owner: np.ndarray
    step_mm: float
    regions: list


def _owners(flat, regions):
    """The index of the region whose planes keep each point (-1: none; the first wins)."""
    flat_owner = np.full(len(flat), -1)
    for i, (planes, _, _) in enumerate(regions):
        inside = np.all([flat * 1000.0 @ np.asarray(nrm)[:2] - off >= -1e-6 for nrm, off in planes], axis=0)
        flat_owner[(flat_owner < 0) & inside] = i
    return flat_owner


def _bed_shares(cell, arms, n, spacing):
    """:class:`_Shares` of the whole bed split among ``arms`` as a model
    would be (:func:`ambots.partition.partition` of a 1 mm slab): a grid of
    at least ``n`` x ``n`` points at most ``spacing`` (m) apart."""
    import manifold3d as m3

    from ambots.partition import partition
    sx, sy, _ = cell.bed.size
    nx, ny = max(n, int(np.ceil(sx / spacing)) + 1), max(n, int(np.ceil(sy / spacing)) + 1)
    u, v = np.meshgrid(np.linspace(-sx / 2, sx / 2, nx), np.linspace(-sy / 2, sy / 2, ny), indexing="ij")
    flat = np.stack([u.ravel(), v.ravel()], axis=1)
    step_mm = 1000.0 * max(sx / (nx - 1), sy / (ny - 1))
    slab = m3.Manifold.cube([sx * 1000.0, sy * 1000.0, 1.0]).translate([-sx * 500.0, -sy * 500.0, 0.0])
    regions = [(part.planes, cell.bed.max_height, part.neighbours)
               for part in partition(slab, cell, arms, check_reach=False)]
    return _Shares(flat, _owners(flat, regions), step_mm, regions)


def _part_shares(names, parts, part_spacing):
    """:class:`_Shares` of a job's parts: a grid ``part_spacing`` (m) apart
    over each part's bounding box, inside its planes, up to its top."""
    by_name = {p.arm.name: p for p in parts}
    regions, chunks = [], []
    for name in names:
        part = by_name.get(name)
        if part is None or part.empty:
            regions.append(([(np.array([0.0, 0.0, 1.0]), np.inf)], 0.0, []))
            continue
        lo, hi = np.asarray(part.manifold.bounding_box()[:3]) / 1000.0, \
            np.asarray(part.manifold.bounding_box()[3:]) / 1000.0
        gx = np.arange(lo[0], hi[0] + part_spacing / 2, part_spacing)
        gy = np.arange(lo[1], hi[1] + part_spacing / 2, part_spacing)
        u, v = np.meshgrid(gx, gy, indexing="ij")
        chunks.append(np.stack([u.ravel(), v.ravel()], axis=1))
        regions.append((part.planes, max(float(hi[2]), 1e-3), list(part.neighbours)))
    flat = np.concatenate(chunks) if chunks else np.zeros((0, 2))
    return _Shares(flat, _owners(flat, regions), 1000.0 * part_spacing, regions)


def _share_tips(grid, n_heights):
    """The grid's points at ``n_heights`` heights from the bed to the
    highest share's top, (tips (M, 3) m, the arm index owning each: -1
    where none does or above its share's top)."""
    regions = grid.regions
    top = max(h for _, h, _ in regions)
    heights = np.linspace(0.0, top, n_heights)
    tips = np.concatenate([np.column_stack([grid.flat, np.full(len(grid.flat), h)]) for h in heights])
    owner = np.tile(grid.flat_owner, n_heights)
    for i, (_, h, _) in enumerate(regions):              # no higher than the part
        owner[(owner == i) & (tips[:, 2] > h + 1e-9)] = -1
    return tips, owner


def _sample_share(cell, arm, mine):
    """:class:`_Sampled` poses of ``arm`` with the nozzle down on the points
    ``mine`` (M, 3) m of the bed frame (its share), IK from its home; a
    redundant arm's also from seeds with its upper-arm roll turned by up to
    0.8 rad.  :class:`UnreachableError` if it reaches none of them."""
    from ambots.workspace import down_in_base, world_to_base
    body = ArmBody.from_arm(arm)
    local = world_to_base(arm, _transform(cell.bed.pose, mine))
    home = np.asarray(arm.profile.home, dtype=float)
    seeds = [home]
    if body.kin.dof > 6:
        # a redundant arm's joints along its self-motion depend on its path
        # (each pose solved from the last, turning back towards home at
        # most 1 rad a metre, kinematics.POSTURE_RAD_PER_M): sample that too,
        # from seeds with the joint before the elbow (the upper arm's roll
        # in a 7-joint arm) turned up to 0.8 rad, and count the worst
        roll = body.kin.dof // 2 - 1
        for delta in (-0.8, -0.4, 0.4, 0.8):
            seed = home.copy()
            seed[roll] = np.clip(seed[roll] + delta, body.kin.lower[roll], body.kin.upper[roll])
            seeds.append(seed)
    sols = [body.kin.ik_batch(local, seed, down_in_base(arm))[:2] for seed in seeds]
    Q = np.concatenate([q for q, _ in sols])
    ok = np.concatenate([k for _, k in sols])
    return _solved(cell, arm, body, np.tile(mine, (len(seeds), 1)), Q, ok, "grid points of its share")


def _planes_between(regions, names):
    """{(i, j): (normal (2,), offset mm)}: the plane between arm i's share
    and arm j's, from i's side (distance n . p - offset, >= 0 on i's side)."""
    plane_of = {}
    for i, (planes, _, others) in enumerate(regions):
        for (nrm, off), other in zip(planes, others):
            if other in names:
                plane_of[i, names.index(other)] = (np.asarray(nrm, dtype=float)[:2], float(off))
    return plane_of


def _to_share(grid, P, i):
    """Horizontal distance (m) from points P to the grid points of share i."""
    Q = grid.flat[grid.flat_owner == i]
    out = np.full(len(P), np.inf)
    for k in range(0, len(P) if len(Q) else 0, 256):
        out[k:k + 256] = np.linalg.norm(P[k:k + 256, None, :2] - Q[None], axis=2).min(axis=1)
    return out


def _facing_side(s, grid, plane, site, other_site, other, band):
    """One arm's side of a pair (:func:`seam_zones_mm`): the protrusions of
    its sampled poses ``s`` (on its own share) towards the other arm (m,
    :func:`_protrusion` along the normal of ``plane`` (normal, offset mm;
    None: along the line between the bases ``site`` -> ``other_site``)),
    which poses count (the nozzle no farther from the plane than the base)
    and their distance (m) to share ``other``."""
    if plane is not None:
        nrm, off = plane
        u = -nrm / np.linalg.norm(nrm)
        # a pose with the nozzle farther from the plane than the arm's
        # own base has the (fixed) base between the nozzle and the
        # plane: the base does not come nearer, whatever the pose
        front = s.tips[:, :2] * 1000.0 @ nrm - off <= site * 1000.0 @ nrm - off
    else:
        u = (other_site - site) / np.linalg.norm(other_site - site)
        front = np.ones(len(s.tips), dtype=bool)
    d = np.full(len(front), np.inf)
    d[front] = _to_share(grid, s.tips[front], other)
    return _protrusion(s, band, u), front, d


#: arms whose seam's normal is more than this off the line between their
#: bases, or off the line from either arm's base to where it works near the
#: seam, stand at an angle to it (:func:`_at_an_angle`)
AT_AN_ANGLE_DEG = 15.0


def _at_an_angle(normal, site_a, site_b, tips):
    """Whether two arms do not face each other along their seam's ``normal``
    (bed xy): the line between their bases ``site_*`` (m), or the line from
    either base to the middle of its nozzle positions near the seam
    (``tips``: one (M, 2) array per arm, m), more than
    :data:`AT_AN_ANGLE_DEG` off the normal.  The protrusions projected on
    the normal are tight for arms that face each other (the default cell's),
    loose for arms beside each other along the seam (a beam's) or at an
    angle to it (four in the corners of a bed, each facing the centre)."""
    n = np.asarray(normal, dtype=float)[:2]
    lines = [np.asarray(site_b, dtype=float) - np.asarray(site_a, dtype=float)]
    lines += [np.mean(t, axis=0) - np.asarray(site, dtype=float)
              for t, site in zip(tips, (site_a, site_b)) if len(t)]
    limit = np.cos(np.radians(AT_AN_ANGLE_DEG))
    return any(abs(float(n @ v)) < limit * np.linalg.norm(n) * np.linalg.norm(v) for v in lines)


def _clearance_zone(side_a, side_b, z_mm, margin_mm, step_mm, chunk=20000):
    """The smallest zone (mm) that every sampled pair of poses of two arms
    whose nozzles are at least that far apart across their seam (sum of the
    two distances) keeps ``margin_mm`` of clearance (all capsules), plus one
    grid step ``step_mm`` for the poses between the samples; only pairs
    nearer than ``z_mm`` are looked at.  ``side_*``: (sampled poses, indices
    of the poses to use, distance (mm) of every pose's nozzle to the seam).

    The answer is the largest sum of a pair that comes within the margin, so
    the pairs are taken from the largest sum down, ``chunk`` at a time, and
    the first chunk with such a pair holds it.  Capsules of the two arms
    that stay apart by the margin in every pose (the boxes they sweep over
    the poses used, grown by their radii, do) are not compared.  Both give
    the answer of comparing every capsule of every pair (the four-arm
    cell's Kinova and UR10 on the 300 mm plate: 59.5 mm, 36 s -> 1-2 s)."""
    (sa, ia, da), (sb, ib, db) = side_a, side_b
    if not len(ia) or not len(ib):
        return float(margin_mm)
    S = da[ia][:, None] + db[ib][None, :]
    I, J = np.nonzero(S < z_mm)
    if not len(I):
        return float(margin_mm)
    order = np.argsort(-S[I, J], kind="stable")
    I, J = I[order], J[order]
    # the capsule pairs that can come within the margin in some pose pair
    ra, rb = np.asarray(sa.body.radii), np.asarray(sb.body.radii)
    lo_a = np.minimum(sa.A[ia], sa.B[ia]).min(axis=0) - ra[:, None]
    hi_a = np.maximum(sa.A[ia], sa.B[ia]).max(axis=0) + ra[:, None]
    lo_b = np.minimum(sb.A[ib], sb.B[ib]).min(axis=0) - rb[:, None]
    hi_b = np.maximum(sb.A[ib], sb.B[ib]).max(axis=0) + rb[:, None]
    gap = np.maximum(np.maximum(lo_b[None] - hi_a[:, None], lo_a[:, None] - hi_b[None]), 0.0)
    ca, cb = np.nonzero(np.linalg.norm(gap, axis=2) < margin_mm / 1000.0)
    if not len(ca):
        return float(margin_mm)
    for k in range(0, len(I), chunk):
        i, j = ia[I[k:k + chunk]], ib[J[k:k + chunk]]
        c = segment_distance(sa.A[i][:, ca], sa.B[i][:, ca], sb.A[j][:, cb], sb.B[j][:, cb]) - ra[ca] - rb[cb]
        bad = c.min(axis=1) < margin_mm / 1000.0
        if bad.any():
            return float(S[I[k:k + chunk], J[k:k + chunk]][bad].max()) + step_mm
    return float(margin_mm)


class CollisionCheck:
    """``is_valid(Q)`` for one arm's planner (its joint moves,
    :class:`~ambots.motion.MotionPlanner`): clear of the bed and, by at
    least ``margin`` m, of every other arm at its last known joint vector
    (:meth:`update`; arms not heard of yet are not checked).  The firmware
    node and the offline simulation (:func:`ambots.sim.simulate`, bed
    only) plan with it."""

    def __init__(self, arm, cell, margin=0.005):
        self.cell, self.margin = cell, margin
        self.body = ArmBody.from_arm(arm)
        self.others = {a.name: ArmBody.from_arm(a) for a in cell.arms if a.name != arm.name}
        self.q_other = {}

    def update(self, name, q):
        self.q_other[name] = np.asarray(q, dtype=float)

    def static(self, Q):
        """The same check without the other arms (they move on; the planner
        waits for them instead of failing)."""
        Q = np.atleast_2d(np.asarray(Q, dtype=float))
        return bed_clearance(self.body, Q, self.cell) >= 0.0

    def __call__(self, Q):
        Q = np.atleast_2d(np.asarray(Q, dtype=float))
        ok = self.static(Q)
        for name, q in list(self.q_other.items()):
            if ok.any():
                ok &= clearance_between(self.body, Q, self.others[name], np.tile(q, (len(Q), 1))) >= self.margin
        return ok

    def explain(self, q):
        """Why joint vector ``q`` fails the check (or ``"clear"``): each
        obstacle it is too close to, with the clearance in mm and the
        closest pair of links, e.g. ``ur10 -34.65 mm (needs >= 5 mm):
        bracelet_link / wrist_2_link``."""
        q = np.asarray(q, dtype=float)[None]
        why = []
        bed = float(bed_clearance(self.body, q, self.cell)[0])
        if bed < 0.0:
            names = [str(n) for n in dict.fromkeys(self.body.names)]
            links = [n for n in names if n != "base_link"]          # bed_clearance skips the base link
            per_link = [float(bed_clearance(self.body, q, self.cell, skip=[m for m in names if m != n])[0])
                        for n in links]
            link = ": " + links[int(np.argmin(per_link))]
            why.append("bed %.2f mm (needs >= 0)%s" % (bed * 1000.0, link))
        for name, qo in sorted(self.q_other.items()):
            other = self.others[name]
            A1, B1, r1 = self.body.capsules(q)
            A2, B2, r2 = other.capsules(qo[None])
            D = capsule_distances(A1, B1, r1, A2, B2, r2)[0]
            i, j = np.unravel_index(int(np.argmin(D)), D.shape)
            if D[i, j] < self.margin:
                why.append("%s %.2f mm (needs >= %g mm): %s / %s" % (name, D[i, j] * 1000.0, self.margin * 1000.0,
                                                                     self.body.names[i], other.names[j]))
        return "; ".join(why) or "clear"
