"""Checks of a sequential print from what the arms executed, independent of
the planner's own checks (the coordinator's approach heights, the report's
box model of the part): the arms' recorded motion (Hermite knots: time,
joints, joint speeds) against the actual beads of the other arms.

Used by the rostest node sequential_test (the real firmware nodes and hub)
and by tests/unit/test_sequential.py (the firmware's runners offline).

* :func:`bursts` -- when an arm laid beads: its turns.
* :func:`closest_to_beads` -- how near an arm's bodies (its collision
  capsules at its recorded joints, the geometry of the arm's URDF) came to
  the beads another arm had laid by then.
* :func:`moves_during` -- how far an arm's joints moved while another laid
  beads (sequential: not at all)."""
import numpy as np
from scipy.spatial import cKDTree

#: a bead's half width (mm): the beads' centre lines are the nozzle's path,
#: the beads as wide as the nozzle's 0.45 mm bead
BEAD_RADIUS_MM = 0.225
#: sampling: points every STEP_MM along beads and along each capsule's axis,
#: motion cut so that no point of the arm moves more than STEP_MM between
#: samples (a lever of REACH_M at the largest joint step)
STEP_MM = 0.5
REACH_M = 1.6
#: the most the sampled distance can exceed the true one (mm): half a step
#: along the beads, half along the axis, one step of motion
SLACK_MM = 2.0 * STEP_MM


def bursts(t, gap_s=1.0):
    """Times ``t`` (s) of an arm's beads -> [(first, last)] of the runs of
    beads with no pause longer than ``gap_s`` (its turns)."""
    t = np.sort(np.asarray(t, dtype=float))
    if not len(t):
        return []
    cut = np.nonzero(np.diff(t) > gap_s)[0]
    starts = np.concatenate([[0], cut + 1])
    ends = np.concatenate([cut, [len(t) - 1]])
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends)]


def hermite(t, Q, V, T):
    """Joint vectors at times ``T`` of the cubic Hermite motion through the
    knots (t, Q, V) (held at the ends)."""
    T = np.clip(np.asarray(T, dtype=float), t[0], t[-1])
    i = np.clip(np.searchsorted(t, T, side="right") - 1, 0, len(t) - 2)
    h = t[i + 1] - t[i]
    s = np.where(h > 0, (T - t[i]) / np.where(h > 0, h, 1.0), 0.0)[:, None]
    h = h[:, None]
    h00, h10 = 2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s
    h01, h11 = -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2
    return h00 * Q[i] + h10 * h * V[i] + h01 * Q[i + 1] + h11 * h * V[i + 1]


def dense(t, Q, V):
    """Times at which to sample the motion: every knot, and between two
    knots enough points that the joints together move at most STEP_MM /
    REACH_M rad (no point of the arm moves more than STEP_MM)."""
    t, Q = np.asarray(t, dtype=float), np.asarray(Q, dtype=float)
    order = np.argsort(t, kind="stable")
    t, Q, V = t[order], Q[order], np.asarray(V, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, Q, V = t[keep], Q[keep], V[keep]
    step = STEP_MM / 1000.0 / REACH_M
    # a cubic between knots may overshoot the chord: count the speeds' share too
    dq = np.abs(np.diff(Q, axis=0)).sum(axis=1) + 0.25 * np.diff(t) * np.abs(V).sum(axis=1)[:-1]
    n = np.maximum(1, np.ceil(dq / step)).astype(int)
    T = np.concatenate([_spread(t[:-1], t[1:], n, closed=False), t[-1:]])
    return t, Q, V, T


def _spread(a, b, n, closed=True):
    """Points a + (b - a) k / n for k = 0 .. n (``closed``) or 0 .. n - 1,
    of every row of a, b ((K,) or (K, 3)) with its own n (K,), concatenated."""
    m = n + 1 if closed else n
    idx = np.repeat(np.arange(len(n)), m)
    k = np.arange(len(idx)) - np.repeat(np.cumsum(m) - m, m)
    u = k / n[idx]
    if np.ndim(a) == 1:
        return a[idx] + u * (b - a)[idx]
    return a[idx] + u[:, None] * (b - a)[idx]


def bead_points(p0, p1):
    """Points (m) every STEP_MM along beads p0 -> p1 (K, 3), m."""
    p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    n = np.maximum(1, np.ceil(np.linalg.norm(p1 - p0, axis=1) * 1000.0 / STEP_MM)).astype(int)
    return _spread(p0, p1, n)


def closest_to_beads(body, trace, beads):
    """Smallest distance (mm) between the arm's capsules and another arm's
    beads laid by then, over the arm's recorded motion; and the time of it.

    ``body``: :class:`ambots.collision.ArmBody` of the arm; ``trace``: (t,
    Q, V) its Hermite knots; ``beads``: (p0 (K, 3) m, p1, t (K,) s) of the
    other arm.  At a sample time the other arm's deposit is taken as every
    bead it laid up to the end of its turn then under way or last done (a
    superset of what was there).  Distances are surface to surface: the
    capsule's radius and :data:`BEAD_RADIUS_MM` subtracted; the sampled
    value exceeds the true one by at most :data:`SLACK_MM`."""
    t, Q, V, T = dense(*trace)
    p0, p1, tb = (np.asarray(v, dtype=float) for v in beads)
    turns = bursts(tb)
    if not turns:
        return float("inf"), None
    ends = np.array([b for _, b in turns])
    starts = np.array([a for a, _ in turns])
    which = np.searchsorted(starts, T, side="right") - 1          # the turn under way or last done
    best, when = float("inf"), None
    for k in range(len(turns)):
        Tk = T[which == k]
        if not len(Tk):
            continue
        laid = tb <= ends[k] + 1e-9
        tree = cKDTree(bead_points(p0[laid], p1[laid]))
        for chunk in np.array_split(Tk, max(1, len(Tk) // 5000)):
            A, B, r = body.capsules(hermite(t, Q, V, chunk))           # (N, C, 3)
            N, C = A.shape[:2]
            # each capsule's midpoint: its distance d bounds the capsule's from
            # below (d - half its length) and above (d); only those that may
            # hold the smallest distance are sampled along their axis
            mid, half = (0.5 * (A + B)).reshape(-1, 3), 0.5 * np.linalg.norm(B - A, axis=2).ravel()
            rad = np.tile(r, N)
            d, _ = tree.query(mid)
            upper = d - rad
            lower = upper - half
            cand = np.nonzero(lower * 1000.0 - BEAD_RADIUS_MM < min(best, upper.min() * 1000.0 - BEAD_RADIUS_MM))[0]
            if not len(cand):
                continue
            a, b = A.reshape(-1, 3)[cand], B.reshape(-1, 3)[cand]
            m = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) * 1000.0 / STEP_MM)).astype(int)
            idx = np.repeat(np.arange(len(m)), m + 1)
            dd, _ = tree.query(_spread(a, b, m))
            dd = (dd - rad[cand][idx]) * 1000.0 - BEAD_RADIUS_MM
            j = int(np.argmin(dd))
            if dd[j] < best:
                best, when = float(dd[j]), float(chunk[cand[idx[j]] // C])
    return best, when


def moves_during(trace, spans):
    """The largest joint change (rad) of an arm's recorded motion inside any
    of the time ``spans`` [(t0, t1)] (another arm's turns)."""
    t, Q, V, T = dense(*trace)
    worst = 0.0
    for a, b in spans:
        inside = T[(T >= a) & (T <= b)]
        if not len(inside):
            continue
        q = hermite(t, Q, V, np.concatenate([[a], inside, [b]]))
        worst = max(worst, float(np.abs(q - q[0]).max()))
    return worst
