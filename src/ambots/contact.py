"""Continuous contact check of executed motion: arm-arm, arm-bed and
arm-part clearance over the whole time line, not only at sample times.

An executed trajectory is a list of knots (t, q, v): the cubic Hermite
motion through them that the one timing law (:mod:`ambots.trajectory`)
commands, or -- without speeds -- linear in joint space between them.
Two facts make the check continuous:

* **Sweep bound.**  A point of the arm's body moves, per unit of joint j's
  rotation, at most its distance from joint j's axis.  That distance is at
  most the chain length from the joint to the point (the fixed offsets of
  the links in between, plus the point's offset in its own link, plus the
  capsule radius): ``rho_j`` of :func:`sweep_radii`, whatever the other
  joints do.  So between knots k and k+1 no point moves more than
  ``sum_j rho_j |q_j(k+1) - q_j(k)|``: :class:`Sweep` keeps that as a
  cumulative length S(t), and ``S(t1) - S(t0)`` bounds every point's path.
* **Interval bound.**  If a clearance is c0 at t0 and c1 at t1 and the two
  bodies together sweep at most D in between, the clearance anywhere in
  [t0, t1] is at least ``min(c0, c1, (c0 + c1 - D) / 2)``.

:func:`scan` starts from a coarse grid and halves every interval whose bound
is below the threshold (contact, or the smallest clearance seen so far) until
either the bound clears it or the bodies sweep at most :data:`RESOLUTION_M`
(2 mm) in it.  So wherever a contact or the closest approach could be, no
point of any arm moves more than 2 mm between two kept samples, and
everywhere else the clearance provably stays above the threshold.  Units:
metres, seconds.
"""
from dataclasses import dataclass

import numpy as np

__all__ = ["RESOLUTION_M", "sweep_radii", "Sweep", "Scan", "scan"]

#: no point of an arm moves more than this between two samples near a contact
#: or near the closest approach (m)
RESOLUTION_M = 0.002
#: first grid step of :func:`scan` (s); refinement takes it from there
COARSE_STEP_S = 1.0


def sweep_radii(body):
    """(n,) bound on the speed of any point of ``body`` (an
    :class:`~ambots.collision.ArmBody`) per unit speed of each movable joint
    (m/rad; 1 for a prismatic joint), independent of the configuration."""
    segs = body.kin.chain.segments
    offsets = np.array([np.linalg.norm(s.origin[:3, 3]) for s in segs])       # link-to-link lengths
    reach = np.maximum(np.linalg.norm(body._a, axis=1), np.linalg.norm(body._b, axis=1)) + body.radii
    link = np.asarray(body.link_index)                 # capsule c hangs on frame link[c] (0 = base)
    out = []
    for s, seg in enumerate(segs):
        if seg.kind == "fixed":
            continue
        if seg.kind == "prismatic":
            out.append(1.0)
            continue
        carried = link >= s + 1                        # joint s sits at the origin of frame s + 1
        if not carried.any():
            out.append(0.0)
            continue
        between = np.array([offsets[s + 1:L].sum() for L in link[carried]])
        out.append(float((between + reach[carried]).max()))
    return np.array(out)


class Sweep:
    """One arm's executed motion: knots ``t`` (K,) s, ``Q`` (K, n) rad and,
    if given, joint speeds ``V`` (K, n) rad/s at the knots (cubic Hermite
    between knots, the commanded motion of :class:`ambots.trajectory.Spline`),
    else linear between knots; held before the first knot and after the
    last.  Knots at the same time keep the last one.  ``radii`` from
    :func:`sweep_radii`."""

    def __init__(self, t, Q, radii, V=None):
        t = np.asarray(t, dtype=float)
        Q = np.asarray(Q, dtype=float)
        keep = np.ones(len(t), dtype=bool)
        keep[:-1] = np.diff(t) > 0
        self.t, self.Q = t[keep], Q[keep]
        self.V = None if V is None else np.asarray(V, dtype=float)[keep]
        radii = np.asarray(radii, dtype=float)
        if self.V is None or len(self.t) < 2:
            path = np.abs(np.diff(self.Q, axis=0))
        else:
            from ambots.trajectory import segment_bounds
            T = np.diff(self.t)
            path = segment_bounds(T, np.diff(self.Q, axis=0), self.V)[0] * T[:, None]
        self.S = np.concatenate([[0.0], np.cumsum(path @ radii)])        #: cumulative sweep bound, m

    def at(self, times):
        """Joint vectors (N, n) at ``times`` (N,)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        if self.V is None or len(self.t) < 2:
            return np.stack([np.interp(times, self.t, self.Q[:, j]) for j in range(self.Q.shape[1])], axis=1)
        from ambots.trajectory import hermite
        return hermite(self.t, self.Q, self.V, times)

    def swept(self, t0, t1):
        """Bound (N,) on how far any point moves between ``t0`` and ``t1`` (N,), m."""
        return np.interp(t1, self.t, self.S) - np.interp(t0, self.t, self.S)


@dataclass
class Scan:
    """Result of :func:`scan`: smallest clearance at a sample (``min``, m, at
    ``t_min`` s), provable lower bound over the whole time span (``bound``, m),
    samples evaluated, samples in contact, and the coarsest resolution left
    where the bound was below the threshold (``resolution``, m)."""
    min: float
    t_min: float
    bound: float
    samples: int
    contacts: int
    resolution: float


def scan(clearance, swept, t_end, contact=0.0, track_min=True, growth=None, resolution=RESOLUTION_M,
         step=COARSE_STEP_S, max_rounds=64, t_start=0.0):
    """Clearance over [``t_start``, ``t_end``], continuously.

    clearance(times (N,)) -> (N,) m; swept(t0, t1) -> (N,) m, the bound on
    how far the bodies move together in each interval; growth(t0, t1) -> (N,)
    m, how much an obstacle grows in each interval (the part), or None.
    Intervals are halved while their bound is below ``contact`` (or, with
    ``track_min``, below the smallest clearance sampled so far) and the
    bodies sweep more than ``resolution`` in them."""
    t = np.unique(np.append(t_start + np.arange(0.0, max(0.0, t_end - t_start), step), max(t_start, t_end)))
    c = clearance(t)
    samples, contacts = len(t), int(np.sum(c < contact))
    k = int(np.argmin(c))
    best, t_best = float(c[k]), float(t[k])
    t0, t1, c0, c1 = t[:-1], t[1:], c[:-1], c[1:]
    bound, coarsest = best, 0.0
    for _ in range(max_rounds):
        if not len(t0):
            break
        D = swept(t0, t1)
        g = growth(t0, t1) if growth is not None else 0.0
        lb = np.minimum(np.minimum(c0 - g, c1), (c0 - g + c1 - D) / 2)
        threshold = max(contact, best) if track_min else contact
        split = (lb < threshold) & (D + g > resolution) & (t1 - t0 > 1e-9)
        done = ~split
        if done.any():
            bound = min(bound, float(lb[done].min()))
            low = done & (lb < threshold)
            if low.any():
                coarsest = max(coarsest, float((D + g)[low].max()))
        t0, t1, c0, c1 = t0[split], t1[split], c0[split], c1[split]
        if not len(t0):
            break
        tm = (t0 + t1) / 2
        cm = clearance(tm)
        samples += len(tm)
        contacts += int(np.sum(cm < contact))
        k = int(np.argmin(cm))
        if cm[k] < best:
            best, t_best = float(cm[k]), float(tm[k])
        t0, t1 = np.concatenate([t0, tm]), np.concatenate([tm, t1])
        c0, c1 = np.concatenate([c0, cm]), np.concatenate([cm, c1])
    else:
        raise RuntimeError("contact scan did not converge in %d rounds" % max_rounds)
    return Scan(best, t_best, min(bound, best), samples, contacts, coarsest)
