"""Joint trajectories for a real controller, without ROS: timing within the
joint limits, stopping on request, and cutting the motion into chunks of
samples (what ``nodes/firmware`` with ``driver:=trajectory`` sends).

Limits (:func:`joint_limits`): per joint, ``velocity`` x ``velocity_scaling``
(capped by the driver's ``max_joint_speed`` if the profile gives one) and
``acceleration`` x ``velocity_scaling``, the fraction of the limits the
planner uses when printing.

The finite-difference measure (:func:`finite_differences`): the speed of a
joint over an interval between two points is its change over the
interval's duration; the acceleration at a point is the change of that
speed from the interval before to the interval after, over the mean of the
two durations; an interval in which nothing moves counts as rest.  This is
what ``python -m ambots export`` checks and what the rostest measures on
the points a controller receives.  :func:`retime` stretches a block's times
(never shortening any) until that measure is within an acceleration limit.

The commanded motion (:class:`Spline`, :func:`smooth`): a block's waypoints
joined by cubic Hermite segments (the block's positions at its times; at a
waypoint the slope of the parabola through it and its neighbours, i.e.
along the path, or zero where the path has a corner -- where it turns by
90 deg or more, or where the nozzle would otherwise leave the planned line
by more than the planner's tolerance -- and at both ends: a block starts
and ends at rest).  The largest speed and acceleration
of every segment are computed exactly (the acceleration of a cubic is linear,
its speed quadratic) and segments are stretched until they are within the
limits.  If a motion's speed and acceleration never exceed ``vmax``/``amax``,
neither does the finite-difference measure of any samples of it (a mean of
speeds is within their range; the difference of two interval means is a
mean of speed changes over at most the distance of the interval midpoints),
so samples of a :class:`Spline` pass :func:`finite_differences` checks at
any sampling.  Blocks are timed with ``ACCEL_SHARE`` of the acceleration
limit; the rest is kept for stopping.

Stopping (:func:`stop_at_line_end`, :func:`stop_now`): motion already sent
to the controller cannot be taken back, so a pause brakes after it: the
path stays the same and only the pace along it slows down (a time warp
``tau(t)`` with ``dtau/dt`` falling linearly from 1 to 0), landing at rest
exactly on the first waypoint ending a G-code line that it can reach within
the acceleration limits.  Joint speed along the warp is ``q'(tau) s`` and
acceleration ``q''(tau) s^2 - c q'(tau)``; the deceleration rate ``c`` is the
largest one the unused share of every joint's acceleration allows over the
braking window.

Streaming (:class:`Stream`): the runner reports every block it starts (or
resumes) with its start time; the stream samples each stretch of motion
from rest to rest on its own grid (``sample_period``) and hands out chunks
of at most ``chunk_duration`` s, each starting with the sample the previous
one ended with, a chunk ahead of the runner's clock.  The extruder's
position (metres of filament pushed since the stream began) follows the
same samples: within a waypoint interval the filament of that interval is
pushed in proportion to the joints' progress along it (in time for an
interval without joint motion: a retraction).

Units: metres, radians, seconds (REP 103).
"""
import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from ambots.protocol import ArmState
from ambots.units import MM

__all__ = ["DEFAULT_SAMPLE_PERIOD", "ACCEL_SHARE", "DriverSpec", "driver_spec", "joint_limits",
           "finite_differences", "retime", "profile_durations", "knot_slopes", "segment_bounds", "hermite", "Spline", "smooth", "SplineTiming", "Motion",
           "stop_at_line_end", "stop_now", "Segment", "Chunk", "Stream"]

#: s between the points of a trajectory for a controller whose profile names no ``sample_period``
DEFAULT_SAMPLE_PERIOD = 0.01
#: share of the acceleration limits used by the planned motion; the rest is kept for braking
ACCEL_SHARE = 0.8
#: times closer than this (s) are the same time
TIME_EPS = 1e-9


# ------------------------------------------------------------- the arm's driver
@dataclass(frozen=True)
class DriverSpec:
    """The real controller's interface of an arm (the profile's ``driver:``)."""
    joint_names: Tuple[str, ...]     #: the controller's joint names, profile joint order
    command_topic: str               #: JointTrajectory topic, relative to the arm's namespace
    sample_period: float             #: s between trajectory points
    max_joint_speed: Optional[float]  #: rad/s, every joint, on this interface (None: no extra cap)
    joint_states_topic: str          #: where the controller publishes its joint states
    extruder_topic: str              #: JointTrajectory topic of the extruder
    extruder_joint: str              #: the extruder's joint name (position: filament pushed, m)


def driver_spec(profile):
    """:class:`DriverSpec` of an :class:`~ambots.config.ArmProfile` (the
    optional keys were checked when the profile was loaded)."""
    o = profile.driver_options
    speed = o.get("max_joint_speed")
    return DriverSpec(tuple(profile.driver_joint_names), profile.driver_command_topic,
                      float(o.get("sample_period", DEFAULT_SAMPLE_PERIOD)),
                      None if speed is None else float(speed),
                      str(o.get("joint_states_topic", "joint_states")),
                      str(o.get("extruder_topic", "extruder_controller/command")),
                      str(o.get("extruder_joint", "extruder")))


def joint_limits(profile):
    """``(vmax, amax)`` (n,) rad/s, rad/s^2: the speeds and accelerations the
    arm uses (``velocity``/``acceleration`` x ``velocity_scaling``), speeds
    capped by the driver's ``max_joint_speed``."""
    scale = profile.velocity_scaling
    vmax = np.array([j.velocity for j in profile.joints], dtype=float) * scale
    cap = profile.driver_options.get("max_joint_speed")
    if cap is not None:
        vmax = np.minimum(vmax, float(cap))
    amax = np.array([j.acceleration for j in profile.joints], dtype=float) * scale
    return vmax, amax


# ------------------------------------------------------------- the measure
def finite_differences(t, Q):
    """Speeds ``V`` (K-1, n) per interval and accelerations ``A`` (K, n) per
    point of the points ``Q`` (K, n) at times ``t`` (K,) (see the module
    docstring); an interval of zero duration in which a joint moves has
    infinite speed."""
    t = np.asarray(t, float)
    Q = np.asarray(Q, float)
    n = Q.shape[1]
    dt = np.diff(t)
    D = np.diff(Q, axis=0)
    moving = np.any(D != 0, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        V = np.where(moving[:, None], D / np.where(dt > 0, dt, 0.0)[:, None], 0.0)
    rest = np.zeros((1, n))
    dV = np.diff(np.concatenate([rest, V, rest]), axis=0)
    Te = np.where(moving, dt, 0.0)
    h = 0.5 * (np.concatenate([[0.0], Te]) + np.concatenate([Te, [0.0]]))
    with np.errstate(invalid="ignore"):
        A = np.where(h[:, None] > 0, dV / np.where(h > 0, h, 1.0)[:, None], 0.0)
    return V, A


def retime(t, Q, amax, max_iter=200):
    """Times (K,) of the waypoints ``Q`` (K, n) of a block, every interval
    stretched as little as this simple scheme finds (never shortened) so that
    the accelerations :func:`finite_differences` measures stay within
    ``amax`` (n,), the block starting and ending at rest.  Intervals without
    joint motion (a retraction, a dwell) keep their duration and count as
    rest.

    Each round stretches both intervals next to every waypoint over the
    limit by the square root of its excess (the acceleration there then
    fits, as if the neighbours did not change); after ``max_iter`` rounds
    whatever is left is removed by stretching the whole block uniformly."""
    t = np.asarray(t, float)
    T = np.diff(t)
    D = np.diff(np.asarray(Q, float), axis=0)
    moving = np.any(D != 0, axis=1) & (T > 0)
    if not moving.any():
        return t
    amax = np.asarray(amax, float)

    def excess(T):
        Te = np.where(moving, T, 0.0)
        V = np.where(moving[:, None], D / np.where(moving, T, 1.0)[:, None], 0.0)
        rest = np.zeros((1, D.shape[1]))
        dV = np.abs(np.diff(np.concatenate([rest, V, rest]), axis=0))
        h = 0.5 * (np.concatenate([[0.0], Te]) + np.concatenate([Te, [0.0]]))
        need = (dV / amax).max(axis=1)
        return np.where(h > 0, need / np.where(h > 0, h, 1.0), 0.0)

    for _ in range(max_iter):
        r = excess(T)
        bad = r > 1.0
        if not bad.any():
            break
        f = np.where(bad, np.sqrt(r) * (1 + 1e-9), 1.0)
        T = np.where(moving, T * np.maximum(f[:-1], f[1:]), T)
    else:
        r = excess(T).max()
        if r > 1.0:
            T = np.where(moving, T * math.sqrt(r) * (1 + 1e-9), T)
    return np.concatenate([t[:1], t[0] + np.cumsum(T)])


# ------------------------------------------------------------- the spline
def knot_slopes(T, D, stop):
    """Slopes (K, n) at the knots of a piecewise cubic through points with
    interval durations ``T`` (K-1,) > 0 and changes ``D`` (K-1, n): at a
    knot, the slope of the parabola through it and its two neighbours
    (``(T2 V1 + T1 V2) / (T1 + T2)``, along the path), 0 where ``stop`` (K,)
    is set (the arm passes that knot at rest)."""
    T = np.asarray(T, float)
    D = np.asarray(D, float)
    K1, n = D.shape
    m = np.zeros((K1 + 1, n))
    if K1 < 2:
        return m
    V = D / T[:, None]
    h1, h2 = T[:-1, None], T[1:, None]
    m[1:-1] = (h2 * V[:-1] + h1 * V[1:]) / (h1 + h2)
    m[np.asarray(stop, bool)] = 0.0
    return m


def _hermite(p0, p1, m0, m1, T, s):
    """Positions of cubic Hermite segments (M, n) at parameter s (scalar)."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * T * m0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * T * m1


def _deviation(tip, Q, T, m, line):
    """How far each segment (K-1,) strays, at a quarter, half and three
    quarters of it: where ``line`` (K-1,), the nozzle's distance (m) from the
    straight line between its positions at the segment's ends (``tip``:
    joints (N, n) -> nozzle (N, 3)); elsewhere the largest joint's distance
    (rad) from the segment's straight line in joint space (a joint move)."""
    K1 = len(T)
    S = (0.25, 0.5, 0.75)
    X = np.stack([_hermite(Q[:-1], Q[1:], m[:-1], m[1:], T[:, None], s) for s in S])      # (3, K-1, n)
    D = Q[1:] - Q[:-1]
    DD = np.maximum(np.einsum("ij,ij->i", D, D), 1e-300)
    R = X - Q[:-1]
    out = np.abs(R - np.einsum("sij,ij->si", R, D)[..., None] / DD[:, None] * D).max(axis=(0, 2))
    if tip is not None and line.any():
        sel = np.nonzero(line)[0]
        P = tip(Q)
        A, B = P[sel], P[sel + 1]
        d = B - A
        L2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-30)
        Xt = tip(X[:, sel].reshape(-1, Q.shape[1])).reshape(len(S), len(sel), 3)
        dev = np.zeros(len(sel))
        for Xi in Xt:
            u = np.clip(np.einsum("ij,ij->i", Xi - A, d) / L2, 0.0, 1.0)
            dev = np.maximum(dev, np.linalg.norm(Xi - (A + u[:, None] * d), axis=1))
        out[sel] = dev
    return out


def segment_bounds(T, D, m):
    """Largest |speed| and |acceleration| (K-1, n) of every cubic Hermite segment."""
    T = T[:, None]
    V = D / T
    m0, m1 = m[:-1], m[1:]
    B = 6 * V - 4 * m0 - 2 * m1            # v(s) = m0 + B s + C s^2, s in [0, 1]
    C = -6 * V + 3 * m0 + 3 * m1
    a0, a1 = B / T, (B + 2 * C) / T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(C != 0, -B / (2 * np.where(C != 0, C, 1.0)), -1.0)
    inside = (s > 0) & (s < 1)
    vs = np.where(inside, np.abs(m0 + B * s + C * s * s), 0.0)
    return np.maximum(np.maximum(np.abs(m0), np.abs(m1)), vs), np.maximum(np.abs(a0), np.abs(a1))


def hermite(t, Q, V, times):
    """Positions (M, n) at ``times`` (M,) of the cubic Hermite motion through
    knots ``t`` (K,) strictly increasing, ``Q`` (K, n), slopes ``V`` (K, n),
    held before the first knot and after the last."""
    t = np.asarray(t, float)
    tau = np.clip(np.atleast_1d(np.asarray(times, float)), t[0], t[-1])
    if len(t) < 2:
        return np.repeat(np.asarray(Q, float)[:1], len(tau), axis=0)
    k = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, len(t) - 2)
    T = (t[k + 1] - t[k])[:, None]
    return _hermite(Q[k], Q[k + 1], V[k], V[k + 1], T, (tau - t[k])[:, None] / T)


class Spline:
    """Cubic Hermite motion through knots: times ``t`` (K,) strictly
    increasing, positions ``Q`` (K, n), slopes ``V`` (K, n); ``E`` (K,)
    extruder positions (m) at the knots; ``idx`` (K,) the block waypoint
    each knot is.  ``vseg``/``aseg`` (K-1, n): each segment's largest
    |speed| and |acceleration| (exact)."""

    def __init__(self, t, Q, V, E=None, idx=None):
        self.t = np.asarray(t, float)
        self.Q = np.asarray(Q, float)
        self.V = np.asarray(V, float)
        self.E = np.zeros(len(self.t)) if E is None else np.asarray(E, float)
        self.idx = np.arange(len(self.t)) if idx is None else np.asarray(idx, int)
        if len(self.t) > 1:
            self.vseg, self.aseg = segment_bounds(np.diff(self.t), np.diff(self.Q, axis=0), self.V)
        else:
            self.vseg = self.aseg = np.zeros((0, self.Q.shape[1]))

    @property
    def start(self):
        return float(self.t[0])

    @property
    def end(self):
        return float(self.t[-1])

    def eval(self, tau):
        """``(q, v, a, e, de)`` at times ``tau`` (M,), clamped to the knots:
        positions, speeds, accelerations (M, n); extruder position and speed (M,)."""
        tau = np.clip(np.atleast_1d(np.asarray(tau, float)), self.t[0], self.t[-1])
        t, Q, V, E = self.t, self.Q, self.V, self.E
        M, n = len(tau), Q.shape[1]
        if len(t) < 2:
            z = np.zeros((M, n))
            return np.repeat(Q[:1], M, axis=0), z, z.copy(), np.full(M, E[0]), np.zeros(M)
        k = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, len(t) - 2)
        T = (t[k + 1] - t[k])[:, None]
        s = (tau - t[k])[:, None] / T
        p0, p1, m0, m1 = Q[k], Q[k + 1], V[k] * T, V[k + 1] * T
        s2, s3 = s * s, s * s * s
        q = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * m1
        v = ((6 * s2 - 6 * s) * p0 + (3 * s2 - 4 * s + 1) * m0 + (-6 * s2 + 6 * s) * p1 + (3 * s2 - 2 * s) * m1) / T
        a = ((12 * s - 6) * p0 + (6 * s - 4) * m0 + (-12 * s + 6) * p1 + (6 * s - 2) * m1) / (T * T)
        # the extruder: the interval's filament in proportion to the joints' progress along it
        D = p1 - p0
        dd = np.einsum("ij,ij->i", D, D)
        moving = dd > 0
        ddm = np.where(moving, dd, 1.0)
        u = np.where(moving, np.clip(np.einsum("ij,ij->i", q - p0, D) / ddm, 0.0, 1.0), s[:, 0])
        du = np.where(moving, np.einsum("ij,ij->i", v, D) / ddm, 1.0 / T[:, 0])
        dE = E[k + 1] - E[k]
        return q, v, a, E[k] + dE * u, dE * du

    def rate_limit(self, tau_a, tau_b, amax):
        """The largest deceleration rate ``c`` (1/s) of a time warp over
        [tau_a, tau_b] that keeps every joint within ``amax``: the acceleration
        not used by the motion over its speed, least over the segments
        touched (inf where nothing moves, 0 where the motion uses the whole
        limit)."""
        if len(self.t) < 2:
            return math.inf
        k0 = max(int(np.searchsorted(self.t, tau_a, side="right")) - 1, 0)
        k1 = min(int(np.searchsorted(self.t, tau_b, side="left")), len(self.t) - 1)
        vs, as_ = self.vseg[k0:max(k1, k0 + 1)], self.aseg[k0:max(k1, k0 + 1)]
        moving = vs > 1e-12
        if not moving.any():
            return math.inf
        spare = np.asarray(amax, float)[None, :] - as_
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(moving, np.maximum(spare, 0.0) / np.where(moving, vs, 1.0), np.inf)
        return float(r.min())


def _groups(t):
    """The last index of every run of equal times of ``t``, and the run of every index."""
    new = np.concatenate([[True], np.diff(t) > TIME_EPS])
    grp = np.cumsum(new) - 1
    last = np.concatenate([np.nonzero(new)[0][1:] - 1, [len(t) - 1]])
    return last, grp


def _progress_peak(T, D, m):
    """Largest rate (K-1,) 1/s at which each cubic Hermite segment advances
    along its chord: ``max_s u'(s)`` with ``u`` the projection of the
    position on the chord (0 at the start, 1 at the end).  A segment of a
    straight G-code move is short, so the nozzle's speed is its length times
    this rate; at a constant pace it is 1/T."""
    DD = np.maximum(np.einsum("ij,ij->i", D, D), 1e-300)
    p0 = np.einsum("ij,ij->i", m[:-1], D) / DD
    p1 = np.einsum("ij,ij->i", m[1:], D) / DD
    B = 6.0 / T - 4 * p0 - 2 * p1            # u'(s) = p0 + B s + C s^2
    C = -6.0 / T + 3 * p0 + 3 * p1
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(C != 0, -B / (2 * np.where(C != 0, C, 1.0)), -1.0)
    inside = (s > 0) & (s < 1)
    mid = np.where(inside, p0 + B * s + C * s * s, -np.inf)
    return np.maximum(np.maximum(p0, p0 + B + C), mid)


def _ratios(T, D, m, vmax, amax, pace=None):
    vs, as_ = segment_bounds(T, D, m)
    r = np.maximum(vs / vmax, np.sqrt(as_ / amax)).max(axis=1)
    if pace is not None:                 # a straight move's nozzle: never above its feedrate
        feed = np.isfinite(pace)
        if feed.any():
            r = np.where(feed, np.maximum(r, np.where(feed, pace, 0.0) * _progress_peak(T, D, m)), r)
    return r


def _stretch(T, D, moving, stop, vmax, amax, max_iter, pace=None):
    """Durations (never shorter) at which every segment is within the limits
    (and, where ``pace`` (K-1,) is finite, advances along its chord no
    faster than once per ``pace`` s: the feedrate's duration)."""
    for _ in range(max_iter):
        r = np.where(moving, _ratios(T, D, knot_slopes(T, D, stop), vmax, amax, pace), 0.0)
        if r.max() <= 1.0:
            return T
        # stretch every segment over a limit, its neighbours a little (their slopes meet it)
        f = np.where(r > 1.0, r * (1 + 1e-9), 1.0)
        g = np.sqrt(np.maximum(np.concatenate([[1.0], f[:-1]]), np.concatenate([f[1:], [1.0]])))
        T = np.where(moving, T * np.maximum(f, g), T)
    for _ in range(3):          # uniformly: speeds scale by 1/f, accelerations by 1/f^2
        worst = float(np.where(moving, _ratios(T, D, knot_slopes(T, D, stop), vmax, amax, pace), 0.0).max())
        if worst <= 1.0:
            break
        T = np.where(moving, T * worst * (1 + 1e-9), T)
    return T


def _junction_speed(D, ell, mv, amax):
    """Path speed (K-2,) at which the cubic can pass each inner knot of a
    path whose direction turns there: passing at speed ``w`` turns the
    velocity by ``w |u_k+1 - u_k|`` per joint, half of it before the knot
    (the knot's slope is the mean of its two intervals'), and a cubic whose
    end slope differs by ``delta`` from its interval's mean speed has an
    acceleration of ``4 delta / T`` there: with ``T = l / w`` (the shorter
    interval) that is ``2 w^2 |du_j| / l`` <= ``amax_j``."""
    U = np.where(mv[:, None], D / np.where(mv, ell, 1.0)[:, None], 0.0)
    du = np.abs(U[1:] - U[:-1])
    shorter = np.minimum(ell[:-1], ell[1:])
    with np.errstate(divide="ignore", invalid="ignore"):
        w2 = np.where(du > 1e-12, amax[None, :] * shorter[:, None] / (2.0 * np.where(du > 1e-12, du, 1.0)), np.inf)
    return np.sqrt(w2.min(axis=1))


def profile_durations(T, D, moving, stop, vmax, amax, pace=None):
    """Interval durations (K-1,) of a look-ahead velocity profile along the
    waypoints: the first guess of :func:`smooth`, as a printer firmware's
    planner times its moves.

    Along the joint-space path (interval k of length ``l_k = |D_k|``, unit
    direction ``u_k``) the path speed is capped per interval by the joint
    speeds (``min_j vmax_j / |u_kj|``) and, where ``pace`` (K-1,) is finite,
    by the feedrate (``l_k / pace_k``), and changes at most at
    ``a_k = min_j amax_j / |u_kj|``.  The speed at each knot is the largest
    that a forward and a backward pass allow, no more than the cubic can
    pass the turn there with (:func:`_junction_speed`; 0 where ``stop``
    (K,) is set and next to an interval without motion); each interval then takes the
    time of its trapezoid (accelerate, cruise, decelerate).  Where the
    acceleration is constant the cubic through knots at these times is
    that parabola, so :func:`_stretch` has little left to do.  Intervals
    without motion keep their duration ``T`` (K-1,)."""
    T = np.asarray(T, float)
    D = np.asarray(D, float)
    K1 = len(T)
    if K1 == 0:
        return T.copy()
    ell = np.linalg.norm(D, axis=1)
    mv = np.asarray(moving, bool) & (ell > 0)
    u = np.abs(D) / np.where(mv, ell, 1.0)[:, None]
    with np.errstate(divide="ignore"):
        acc = np.where(mv, np.min(np.where(u > 0, amax[None, :] / np.where(u > 0, u, 1.0), np.inf), axis=1), np.inf)
        cap = np.where(mv, np.min(np.where(u > 0, vmax[None, :] / np.where(u > 0, u, 1.0), np.inf), axis=1), 0.0)
    if pace is not None:
        pace = np.asarray(pace, float)
        fed = mv & np.isfinite(pace) & (pace > 0)
        cap = np.where(fed, np.minimum(cap, ell / np.where(fed, pace, 1.0)), cap)
    w = np.zeros(K1 + 1)                          # path speed at the knots
    w[1:-1] = np.minimum(cap[:-1], cap[1:])
    if K1 > 1:                                    # at a turn: no faster than the cubic can follow it
        w[1:-1] = np.minimum(w[1:-1], _junction_speed(D, ell, mv, amax))
    still = np.asarray(stop, bool).copy()
    still[:-1] |= ~mv
    still[1:] |= ~mv
    w[still] = 0.0
    for k in range(K1):                           # forward: reachable from the knot before
        if mv[k]:
            w[k + 1] = min(w[k + 1], math.sqrt(w[k] ** 2 + 2.0 * acc[k] * ell[k]))
    for k in range(K1 - 1, -1, -1):               # backward: able to slow down for the next
        if mv[k]:
            w[k] = min(w[k], math.sqrt(w[k + 1] ** 2 + 2.0 * acc[k] * ell[k]))
    a = np.where(mv, acc, 1.0)
    w0, w1 = w[:-1], w[1:]
    peak = np.sqrt(np.maximum((2.0 * a * ell + w0 ** 2 + w1 ** 2) / 2.0, 0.0))
    c = np.where(mv, np.maximum(cap, 1e-12), 1.0)
    triangle = (2.0 * peak - w0 - w1) / a
    cruise = ((c - w0) + (c - w1)) / a + np.maximum(ell - (c * c - w0 * w0) / (2 * a) - (c * c - w1 * w1) / (2 * a),
                                                    0.0) / c
    out = np.where(peak <= c, triangle, cruise)
    return np.where(mv, np.maximum(out, 1e-9), T)


def smooth(t, Q, vmax, amax, E=None, tip=None, tolerance=1e-4, line=None, joint_tolerance=1e-3,
           max_iter=100):
    """A block's waypoints ``Q`` (K, n) planned at times ``t`` (K,) ->
    ``(times (K,), Spline)``: times never shorter than ``t`` at which the
    cubic through the waypoints (:func:`knot_slopes`) stays within ``vmax``
    and ``amax`` everywhere; ``E`` (K,) extruder positions.  Along a
    straight G-code move (``line``) the nozzle also never runs faster than
    ``t`` says (the feedrate): each segment advances along its chord at
    most once per its planned duration (:func:`_progress_peak`), so the
    nozzle keeps the feedrate between corners and ramps up and down at them
    within the limits, never overshooting it.

    The arm passes at rest (slope 0) the waypoints where the joint-space
    path turns by 90 deg or more (its two intervals' changes have a
    dot product <= 0), and the waypoints next to a segment that
    strays from its straight line -- at a corner of the path: a segment of
    a straight G-code move (``line`` (K,), per interval, with ``tip``:
    joints (N, n) -> nozzle positions (N, 3)) whose nozzle leaves the line
    between its ends by more than ``tolerance`` (m), any other (a joint
    move) whose joints leave the joint-space line by more than
    ``joint_tolerance`` (rad).  Such a segment then follows the joint-space
    line between its ends, which the planner checked.  The arm also rests
    at both ends and next to intervals without joint motion.  Waypoints at
    the same time share one knot (they must be equal)."""
    Q = np.asarray(Q, float)
    vmax, amax = np.asarray(vmax, float), np.asarray(amax, float)
    t_feed = np.asarray(t, float)
    last, grp = _groups(t_feed)
    tu, Qu = t_feed[last], Q[last]
    Eu = None if E is None else np.asarray(E, float)[last]
    if len(tu) < 2:
        return t_feed.copy(), Spline(tu, Qu, np.zeros_like(Qu), Eu, last)
    T_feed = np.diff(tu)
    D = np.diff(Qu, axis=0)
    moving = np.any(D != 0, axis=1)
    cart = np.zeros(len(T_feed), bool) if line is None or tip is None else np.asarray(line, bool)[last[1:]]
    limit = np.where(cart, tolerance, joint_tolerance)
    # a segment of a straight move takes at least the duration its feedrate gives
    # (the waypoints' times as planned): its nozzle never runs faster than that
    pace = np.where(cart & moving, T_feed, np.inf)
    pace = np.where(pace > 0, pace, np.inf)
    stop = np.zeros(len(tu), bool)
    stop[0] = stop[-1] = True
    stop[1:-1] = ~moving[:-1] | ~moving[1:]
    # a turn of 90 deg or more: none of the speed coming in carries on along
    # the way out, and passing it would only make the cubic bulge (and run
    # slower than stopping there: the look-ahead's corner law)
    nd = np.linalg.norm(D, axis=1)
    stop[1:-1] |= np.einsum("ij,ij->i", D[:-1], D[1:]) <= 1e-9 * nd[:-1] * nd[1:]
    while True:
        # a first guess from a look-ahead profile, then exactly within the limits
        T = _stretch(profile_durations(T_feed, D, moving, stop, vmax, amax, pace), D, moving, stop, vmax, amax,
                     max_iter, pace)
        m = knot_slopes(T, D, stop)
        off = np.nonzero(moving & (_deviation(tip, Qu, T, m, cart) > limit) & ~(stop[:-1] & stop[1:]))[0]
        if not len(off):
            break
        # stop the end whose slope turns away most from the segment's direction
        u = D[off] / np.linalg.norm(D[off], axis=1)[:, None]
        side = []
        for end in (off, off + 1):
            x = m[end] * T[off, None]
            side.append(np.where(stop[end], -1.0, np.linalg.norm(x - np.einsum("ij,ij->i", x, u)[:, None] * u,
                                                                  axis=1)))
        stop[np.where(side[0] >= side[1], off, off + 1)] = True
    tn = tu[0] + np.concatenate([[0.0], np.cumsum(T)])
    return tn[grp], Spline(tn, Qu, knot_slopes(T, D, stop), Eu, last)


def block_filament(block):
    """Extruder positions (K,) m at a block's waypoints, 0 at its start."""
    e = np.asarray(block.e_mm, float).copy()
    if len(e):
        e[0] = 0.0
    return np.cumsum(e) * MM


class SplineTiming:
    """A planner's timing hook (:attr:`ambots.motion.MotionPlanner.timing`):
    re-times a planned block with :func:`smooth` within ``vmax`` and
    ``share`` x ``amax`` (the nozzle within ``tolerance`` m of the planned
    lines, ``tip``: joints -> nozzle positions) and attaches its
    :class:`Motion` (``block.motion``)."""

    def __init__(self, vmax, amax, share=ACCEL_SHARE, tip=None, tolerance=1e-4):
        self.vmax, self.amax, self.share = np.asarray(vmax, float), np.asarray(amax, float), float(share)
        self.tip, self.tolerance = tip, float(tolerance)

    @classmethod
    def for_planner(cls, planner, share=ACCEL_SHARE):
        """The hook for a :class:`~ambots.motion.MotionPlanner`: its arm's
        :func:`joint_limits`, its kinematics and path tolerance."""
        vmax, amax = joint_limits(planner.arm.profile)
        return cls(vmax, amax, share, lambda Q: planner.kin.fk_batch(Q)[:, :3, 3], planner.tolerance)

    def spline(self, t, Q, E=None, line=None):
        """:func:`smooth` with this timing's limits."""
        return smooth(t, Q, self.vmax, self.share * self.amax, E, self.tip, self.tolerance, line)

    def __call__(self, block, scale=1.0):
        """Time ``block`` (in place; returned); ``scale`` >= 1 then stretches
        the timed motion (speeds / scale, accelerations / scale^2: an arm
        running slower than planned)."""
        if len(block.t) < 2:
            block.motion = None
            return block
        t, spline = self.spline(block.t, block.Q, block_filament(block), block.cartesian)
        if scale != 1.0:
            t = t[0] + (t - t[0]) * scale
            spline = Spline(spline.t[0] + (spline.t - spline.t[0]) * scale, spline.Q, spline.V / scale,
                            spline.E, spline.idx)
        block.t = t
        block.motion = Motion(spline)
        return block


# ------------------------------------------------------------- motion and stops
@dataclass
class _Piece:
    """Part of a :class:`Motion` over block times [start, end): a spline
    (block time = spline time + shift), braking after ``t_b`` at rate ``c``
    (``tau = tau_b + s - c s^2 / 2``, s = t - t_b) if ``c`` is set."""
    start: float
    end: float
    spline: Spline
    shift: float = 0.0
    t_b: Optional[float] = None
    tau_b: Optional[float] = None
    c: Optional[float] = None
    freeze_e: bool = False       #: the extruder stops where braking begins
    stop_knot: Optional[int] = None
    tau_stop: Optional[float] = None

    def eval(self, t):
        sp = self.spline
        if self.c is None:
            return sp.eval(t - self.shift)
        s = np.maximum(t - self.t_b, 0.0)
        braking = t > self.t_b
        s = np.minimum(s, 1.0 / self.c)
        tau = np.where(braking, self.tau_b + s - 0.5 * self.c * s * s, t - self.shift)
        if self.tau_stop is not None:             # at rest exactly on the waypoint
            tau = np.where(s >= (1.0 - 1e-9) / self.c, self.tau_stop, tau)
        sig = np.where(braking, 1.0 - self.c * s, 1.0)
        dsig = np.where(braking & (s < 1.0 / self.c), -self.c, 0.0)
        q, v, a, e, de = sp.eval(tau)
        a = a * (sig * sig)[:, None] + v * dsig[:, None]
        v = v * sig[:, None]
        de = de * sig
        if self.freeze_e:
            e0 = sp.eval(np.array([self.start - self.shift]))[3][0]
            e, de = np.full_like(e, e0), np.zeros_like(de)
        return q, v, a, e, de


class Motion:
    """The commanded motion of one block as a function of block time: the
    block's :class:`Spline`, then -- after a stop -- braking pieces and the
    rest re-timed from rest.  Before its start and after its end it holds."""

    def __init__(self, spline):
        self.pieces: List[_Piece] = [_Piece(spline.start, spline.end, spline)]

    @property
    def end(self):
        return self.pieces[-1].end

    def eval(self, t):
        """``(q, v, a, e, de)`` at block times ``t`` (M,) (see :meth:`Spline.eval`)."""
        t = np.clip(np.atleast_1d(np.asarray(t, float)), self.pieces[0].start, self.end)
        starts = np.array([p.start for p in self.pieces])
        which = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(self.pieces) - 1)
        out = None
        for i in np.unique(which):
            sel = which == i
            part = self.pieces[i].eval(np.minimum(t[sel], self.pieces[i].end))
            if out is None:
                out = [np.zeros((len(t),) + x.shape[1:]) for x in part]
            for o, x in zip(out, part):
                o[sel] = x
        return tuple(out)

    def rest_after(self, t):
        """The first block time after ``t`` at which the motion is at rest."""
        for p in self.pieces:
            if p.c is not None and p.end > t + TIME_EPS:
                return p.end
        return self.end

    def _piece_at(self, t):
        for p in reversed(self.pieces):
            if p.start <= t + TIME_EPS:
                return p
        return self.pieces[0]


def _brake_piece(p, H, tau_b, c, freeze_e=False):
    t_b = tau_b + p.shift
    end = t_b + (1.0 / c if math.isfinite(c) else 0.0)
    return _Piece(H, max(end, H), p.spline, p.shift, t_b, tau_b, c if math.isfinite(c) else None, freeze_e)


def stop_at_line_end(block, H, timing, line_ends_only=True):
    """Brake ``block`` (timed by :class:`SplineTiming`) to rest at the first
    waypoint ending a G-code line (or the block's end) at block time >= ``H``
    (the motion up to ``H`` is committed) that it can reach within the
    acceleration limits of ``timing`` (the :class:`SplineTiming` that timed
    it); with ``line_ends_only`` False (an operator's stop, A12) at the
    first waypoint it can reach, wherever it is on its line.  Changes ``block.t`` after ``H`` and ``block.motion``: braking to
    that waypoint, the rest of the block re-timed from rest.  Returns the
    waypoint's index (the runner pauses there)."""
    amax = timing.amax
    m = block.motion
    K = len(block.t)
    if m is None or H >= m.end - TIME_EPS:
        return K - 1
    p = m._piece_at(H)
    if p.c is not None:                          # braking already: it stops where planned
        return p.stop_knot
    sp = p.spline
    tauH = H - p.shift
    last = int(sp.idx[-1])
    for u, j in enumerate(sp.idx):
        j = int(j)
        if block.t[j] < H - TIME_EPS or (line_ends_only and not (block.line_end[j] or j == last)):
            continue
        if j == last:
            return j                              # the block ends at rest anyway
        tau_j = sp.t[u]
        c = sp.rate_limit(tauH, tau_j, amax)
        if not (c == math.inf or (c > 0 and tau_j - tauH >= 0.5 / c)):
            continue
        tau_b = tau_j - (0.5 / c if math.isfinite(c) else 0.0)
        brake = _brake_piece(p, H, tau_b, c)
        brake.stop_knot, brake.tau_stop = j, tau_j
        T_stop = brake.end
        # waypoints between H and j: their times along the warp
        old = block.t.copy()
        mid = (old > H + TIME_EPS) & (np.arange(K) < j)
        if mid.any() and brake.c is not None:
            tau = old[mid] - p.shift
            late = tau > tau_b
            s = np.where(late, (1 - np.sqrt(np.maximum(0.0, 1 - 2 * brake.c * (tau - tau_b)))) / brake.c, 0.0)
            block.t[mid] = np.where(late, brake.t_b + s, old[mid])
        # the rest, from rest at j
        rest = slice(j, last + 1)
        E = block_filament(block)
        tr, spr = timing.spline(old[rest] - old[j], block.Q[rest], E[rest], block.cartesian[rest])
        spr.idx = spr.idx + j
        block.t[rest] = T_stop + tr
        p.end = H
        pieces = [q for q in m.pieces if q is not p or H > p.start + TIME_EPS]
        m.pieces = pieces + [brake, _Piece(T_stop, T_stop + spr.end, spr, T_stop)]
        return j
    return last


def stop_now(motion, H, amax):
    """Brake ``motion`` to rest as soon as the acceleration limits allow
    after block time ``H``, the extruder stopping at ``H``; the motion ends
    there.  Returns the block time of the stop."""
    if motion is None:
        return None
    if H >= motion.end - TIME_EPS:
        return motion.end
    p = motion._piece_at(H)
    if p.c is not None:                          # braking already: stop where planned
        motion.pieces = motion.pieces[:motion.pieces.index(p) + 1]
        return p.end
    sp = p.spline
    tauH = H - p.shift
    w = 0.05
    while True:
        tau_end = min(tauH + w, sp.end)
        c = sp.rate_limit(tauH, tau_end, amax)
        ok = c == math.inf or (c > 0 and 0.5 / c <= tau_end - tauH)
        if ok or tau_end >= sp.end:
            break
        w *= 2
    # braking from H (c inf: nothing moves, the stop is at H); else no earlier stop than the end, at rest
    brake = _brake_piece(p, H, tauH, c, True) if ok else _brake_piece(p, H, sp.end, math.inf, True)
    p.end = H
    motion.pieces = [q for q in motion.pieces if q is not p or H > p.start + TIME_EPS] + [brake]
    return brake.end


# ------------------------------------------------------------- streaming
@dataclass
class Segment:
    """One stretch of a block's motion from rest to rest, sampled from block
    time ``tau0`` every ``dt`` s; sample i is due at the runner's time
    ``start_time + i dt`` (``t0 + tau0``, or up to one sample later: never
    before the previous stretch's last sample, which the grid rounds up);
    ``n`` the last sample; ``sent`` the last sample handed out (-1: none);
    ``e0`` the extruder position at the block's start."""
    block: object
    t0: float
    tau0: float
    end: float
    n: int
    e0: float
    moving: bool
    sent: int = -1
    start_time: float = 0.0


@dataclass
class Chunk:
    """Samples ``first`` .. ``first + len(q) - 1`` of a :class:`Segment`:
    positions, speeds, accelerations (M, n), extruder position and speed (M,)."""
    segment: Segment
    first: int
    q: np.ndarray
    v: np.ndarray
    a: np.ndarray
    e: np.ndarray
    de: np.ndarray

    @property
    def last(self):
        return self.first + len(self.q) - 1


class Stream:
    """The runner's motion as chunks for a controller (see the module
    docstring).  Give :meth:`started` to the runner as its ``on_motion``;
    call :meth:`update` with the runner's clock after every step."""

    def __init__(self, sample_period, chunk_duration=0.5, ahead=None):
        self.dt = float(sample_period)
        self.chunk_n = max(1, int(round(float(chunk_duration) / self.dt)))
        self.ahead = float(chunk_duration if ahead is None else ahead)
        self.cur: Optional[Segment] = None
        self._events = []
        self._e_block = 0.0           # extruder position at the start of the current block
        self._moved_until = None

    # ----------------------------------------------------- the runner's side
    def started(self, block, t0, k):
        """The runner starts (k = 0) or resumes (at waypoint k) ``block`` at time ``t0``."""
        self._events.append((block, float(t0), int(k)))

    def _segment(self, block, t0, k):
        if self.cur is not None and self.cur.block is not block:
            cur = self.cur
            self._e_block = cur.e0 + float(cur.block.motion.eval(np.array([cur.end]))[3][0]) \
                if cur.block.motion is not None else cur.e0
        m = block.motion
        if m is None:
            return Segment(block, t0, 0.0, 0.0, 0, self._e_block, False, 0, t0)
        tau0 = float(block.t[k])
        end = m.rest_after(tau0)
        n = max(0, int(math.ceil((end - tau0) / self.dt - 1e-9)))
        k1 = int(np.searchsorted(block.t, end, side="right")) - 1
        moving = bool(np.ptp(block.Q[k:k1 + 1], axis=0).max(initial=0.0) > 0
                      or np.any(np.asarray(block.e_mm[k + 1:k1 + 1]) != 0))
        go = moving and n > 0
        start = t0 + tau0
        prev = self.idle_after()
        if go and prev is not None:
            start = max(start, prev)
        return Segment(block, t0, tau0, end, n, self._e_block, go, -1 if go else n, start)

    def _take(self, seg, upto):
        out = []
        upto = min(upto, seg.n)
        while seg.sent < upto:
            a = max(seg.sent, 0)
            b = min(a + self.chunk_n, upto) if seg.sent >= 0 else min(self.chunk_n, upto)
            i = np.arange(a, b + 1)
            # past the stretch's end (the last sample, on the grid) it holds at rest
            q, v, acc, e, de = seg.block.motion.eval(np.minimum(seg.tau0 + i * self.dt, seg.end))
            out.append(Chunk(seg, a, q, v, acc, seg.e0 + e, de))
            seg.sent = b
            self._note(seg)
        return out

    def update(self, now):
        """Chunks due by the runner's time ``now`` (s): the rest of every
        stretch the runner has moved on from, and the current one up to
        ``ahead`` s past ``now``."""
        out = []
        for block, t0, k in self._events:
            if self.cur is not None:
                out += self._take(self.cur, self.cur.n)
            self.cur = self._segment(block, t0, k)
        self._events.clear()
        seg = self.cur
        if seg is not None and seg.sent < seg.n:
            need = int(math.ceil((now + self.ahead - seg.start_time) / self.dt))
            if seg.sent < need:              # a whole chunk at a time
                out += self._take(seg, max(seg.sent, 0) + self.chunk_n)
        return out

    def horizon(self, block, t0, now):
        """Block time up to which ``block`` (started at ``t0``) is committed: sent, or reached by ``now``."""
        seg = self.cur
        if seg is not None and seg.block is block and abs(seg.t0 - t0) < TIME_EPS and seg.sent >= 0:
            return max(seg.tau0 + seg.sent * self.dt, now - t0)
        return max(now - t0, float(block.t[0]))

    def pause(self, runner, now, timing):
        """The runner was asked to pause (or stop: ``runner.stop_requested``)
        while moving: plan its stop after what is committed; returns the
        waypoint to pause at (for ``runner.pause_at``) or None when there is
        nothing to brake."""
        b = runner.block
        if b is None or getattr(b, "motion", None) is None:
            return None
        j = stop_at_line_end(b, self.horizon(b, runner.block_t0, now), timing,
                             line_ends_only=not runner.stop_requested)
        seg = self.cur
        if seg is not None and seg.block is b:          # the stretch now ends at the stop
            seg.end = b.motion.rest_after(seg.tau0)
            seg.n = max(seg.sent, int(math.ceil((seg.end - seg.tau0) / self.dt - 1e-9)))
        return j

    def abort(self, runner, now, amax):
        """The runner drops the block it moves in (A4): brake to rest as soon
        as possible after what is committed, extruder stopped.  Returns the
        joints where the arm comes to rest (or None if it was not moving)."""
        b = runner.block
        if b is None or getattr(b, "motion", None) is None or runner.state is not ArmState.PRINTING:
            return None
        T = stop_now(b.motion, self.horizon(b, runner.block_t0, now), amax)
        seg = self.cur
        if seg is not None and seg.block is b:
            seg.end = T
            seg.n = max(seg.sent, int(math.ceil((seg.end - seg.tau0) / self.dt - 1e-9)))
        return b.motion.eval(np.array([T]))[0][0]

    def idle_after(self):
        """The runner's time at which the last stretch of motion handed out
        ends (None: none yet)."""
        return self._moved_until

    def _note(self, seg):
        if seg.moving and seg.sent >= 0:
            self._moved_until = seg.start_time + seg.sent * self.dt
