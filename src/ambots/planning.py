"""Joint-space motion planning for an arm's travel moves (OMPL, no MoveIt).

* :class:`JointPlanner` -- plans a collision-free joint path between two joint
  vectors.  The caller supplies a *vectorised* validity function
  ``is_valid(Q) -> bool mask (N,)`` for ``(N, n)`` joint vectors (collision
  checks against the bed, the other arms, the part...).  The planner first
  tries the straight joint segment (one batched ``is_valid`` call); only if it
  is blocked does it run OMPL's RRTConnect in a ``RealVectorStateSpace``, then
  shortcuts the result and verifies the final path with one more batched call.
* :func:`interpolate` -- denser waypoints, at most ``max_step`` rad per joint
  between consecutive points.
* :func:`time_parametrize` -- waypoint times under per-joint velocity (and
  optionally acceleration) limits.

Segments are straight lines in joint space and are checked by sampling at
``resolution`` rad in the max-norm (no joint moves more than ``resolution``
between two checked samples).  OMPL checks states one at a time; here its
motion validator is a Python subclass that checks a whole segment with one
batched ``is_valid`` call, so OMPL's per-state checker is only used for the
few single states RRTConnect looks at.

OMPL (``pip install ompl``) is imported lazily: everything but the OMPL
fallback of :meth:`JointPlanner.plan` works without it.  All OMPL objects live
only inside one call of ``JointPlanner._ompl_plan`` and are released before it
returns (its nanobind bindings report "leaked instances" at interpreter exit
for any object still alive).

Units: radians (or metres for prismatic joints), seconds.
"""
import math
import time

import numpy as np

from ambots.errors import AmbotsError

__all__ = ["PlanningError", "JointPlanner", "interpolate", "time_parametrize", "set_ompl_log_level"]


class PlanningError(AmbotsError):
    """No path could be planned.  Attributes: ``reason`` (``start_limits``,
    ``goal_limits``, ``start_invalid``, ``goal_invalid``, ``no_path``,
    ``path_invalid``), ``q_start``, ``q_goal`` (arrays or None), ``message``."""

    def __init__(self, reason, message, q_start=None, q_goal=None):
        self.reason, self.message = reason, message
        self.q_start = None if q_start is None else np.array(q_start, float)
        self.q_goal = None if q_goal is None else np.array(q_goal, float)
        super().__init__(message)


def _fmt(q):
    """A joint vector rounded for messages: ``[0.1, -1.571, 3.142]``."""
    return "[%s]" % ", ".join("%.4g" % round(float(v), 4) for v in np.ravel(q))


# ---------------------------------------------------------------------------
# OMPL access (lazy)

_LOG_LEVELS = {"none": "LOG_NONE", "error": "LOG_ERROR", "warn": "LOG_WARN",
               "info": "LOG_INFO", "debug": "LOG_DEBUG"}
_MV_CLASS = None


def _ompl():
    from ompl import base as ob, geometric as og, util as ou
    return ob, og, ou


def set_ompl_log_level(level="warn"):
    """Set OMPL's (process-wide) console log level: ``"none"``, ``"error"``,
    ``"warn"`` (default), ``"info"``, ``"debug"`` or an ``ompl.util.LogLevel``."""
    ou = _ompl()[2]
    if isinstance(level, str):
        try:
            level = getattr(ou, _LOG_LEVELS[level.lower()])
        except KeyError:
            raise ValueError("OMPL log level %r: expected one of %s" % (level, ", ".join(_LOG_LEVELS))) from None
    ou.setLogLevel(level)


def _motion_validator_class():
    """A Python ``ompl.base.MotionValidator`` that checks a whole segment with
    one batched call (defined on first use so the module imports without OMPL)."""
    global _MV_CLASS
    if _MV_CLASS is None:
        ob = _ompl()[0]

        class BatchedMotionValidator(ob.MotionValidator):
            def __init__(self, si, check):
                super().__init__(si)
                self.check = check

            def checkMotion(self, s1, s2):
                return self.check(s1, s2)

        _MV_CLASS = BatchedMotionValidator
    return _MV_CLASS


class _Callbacks:
    """The Python side of OMPL's callbacks.  An exception raised by the
    caller's ``is_valid`` inside OMPL is recorded (the state is reported
    invalid), planning is stopped, and the exception is re-raised afterwards;
    the callback frames, which hold OMPL objects, are cleared first."""

    def __init__(self, planner, deadline):
        self.planner, self.n, self.deadline = planner, planner.dof, deadline
        self.error, self.frames = None, []
        self.states = self.motions = 0

    def _fail(self, exc):
        if self.error is None:
            self.error = exc
        tb = exc.__traceback__
        self.frames.append(tb.tb_frame)
        exc.__traceback__ = tb.tb_next   # drop the callback's own frame

    def state(self, s):
        try:
            self.states += 1
            q = np.array(s[0:self.n], float)
            return self.error is None and bool(self.planner.valid(q[None])[0])
        except BaseException as exc:   # noqa: B902 -- re-raised after planning
            self._fail(exc)
            return False

    def motion(self, s1, s2):
        try:
            self.motions += 1
            return self.error is None and self.planner.segment_clear(s1[0:self.n], s2[0:self.n])
        except BaseException as exc:   # noqa: B902
            self._fail(exc)
            return False

    def stop(self):
        return self.error is not None or time.monotonic() > self.deadline

    def release(self):
        """Clear the finished callback frames; return the recorded exception."""
        for f in self.frames:
            try:
                f.clear()
            except RuntimeError:  # pragma: no cover - frame still running
                pass
        self.frames = []
        exc, self.error = self.error, None
        return exc


# ---------------------------------------------------------------------------
# straight joint segments

def _densify(path, step):
    """Points along the polyline ``path`` (M, n) so that no joint moves more
    than ``step`` between consecutive points; original waypoints kept exactly.
    Returns ``(Q, seg)``: the points and, for each, the index of the segment
    it starts on (the last point gets ``M - 1``)."""
    P = np.asarray(path, float)
    M = len(P)
    if M < 2:
        return P.copy(), np.zeros(M, int)
    d = np.abs(np.diff(P, axis=0)).max(axis=1)
    k = np.maximum(1, np.ceil(d / step * (1.0 - 1e-12))).astype(np.int64)
    seg = np.repeat(np.arange(M - 1), k)
    start = np.repeat(np.cumsum(k) - k, k)
    t = (np.arange(len(seg)) - start) / np.repeat(k, k)
    Q = P[seg] + (P[seg + 1] - P[seg]) * t[:, None]
    return np.vstack([Q, P[-1:]]), np.append(seg, M - 1)


def _dedupe(P, tol=1e-12):
    """``P`` without waypoints equal (within ``tol``) to the previous one; the
    first and last waypoints are kept exactly."""
    keep = np.concatenate([[True], np.abs(np.diff(P, axis=0)).max(axis=1) > tol])
    Q = P[keep]
    Q[-1] = P[-1]
    return Q


def interpolate(path, max_step):
    """Denser waypoints along ``path`` (M, n): straight joint-space pieces, at
    most ``max_step`` (rad) per joint between consecutive points.  The given
    waypoints are kept exactly; a path of one point is returned as is."""
    P = np.asarray(path, float)
    if P.ndim != 2 or len(P) < 1:
        raise ValueError("path must be an (M, n) array with M >= 1, got shape %s" % (P.shape,))
    if not max_step > 0:
        raise ValueError("max_step must be > 0, got %r" % (max_step,))
    return _densify(P, float(max_step))[0]


def time_parametrize(path, vmax, amax=None):
    """Times ``(M,)`` from 0 for the waypoints of ``path`` (M, n), moving in a
    straight joint-space line between consecutive waypoints with all joints
    synchronised, so that no joint exceeds ``vmax`` (n,) (rad/s) and, if
    ``amax`` (n,) (rad/s^2) is given, no joint exceeds its acceleration: each
    segment is then a trapezoidal (or triangular) velocity profile from rest
    to rest (the arm stops at every waypoint).

    Without ``amax`` a segment takes ``max_j |dq_j| / vmax_j``.  With it, the
    common path parameter s in [0, 1] is limited to ``V = min_j vmax_j/|dq_j|``
    and ``A = min_j amax_j/|dq_j|``: ``T = 2 sqrt(1/A)`` if ``V^2 >= A``
    (never reaches V), else ``1/V + V/A``.

    Times are strictly increasing wherever consecutive waypoints differ (a
    repeated waypoint gets the same time)."""
    P = np.asarray(path, float)
    if P.ndim != 2 or len(P) < 1:
        raise ValueError("path must be an (M, n) array with M >= 1, got shape %s" % (P.shape,))
    n = P.shape[1]

    def limit(x, name):
        x = np.broadcast_to(np.asarray(x, float), (n,))
        if not (np.all(np.isfinite(x)) and np.all(x > 0)):
            raise ValueError("%s must be finite and > 0 for each of the %d joints, got %s" % (name, n, x))
        return x

    vmax = limit(vmax, "vmax")
    d = np.abs(np.diff(P, axis=0))
    tv = (d / vmax).max(axis=1) if n else np.zeros(len(d))   # = 1/V
    if amax is None:
        T = tv
    else:
        amax = limit(amax, "amax")
        ta2 = (d / amax).max(axis=1) if n else np.zeros(len(d))   # = 1/A
        triangle = tv * tv <= ta2
        with np.errstate(divide="ignore", invalid="ignore"):
            T = np.where(triangle, 2.0 * np.sqrt(ta2), tv + ta2 / np.where(tv > 0, tv, 1.0))
    return np.concatenate([[0.0], np.cumsum(T)])


# ---------------------------------------------------------------------------

class JointPlanner:
    """Collision-free joint-space paths for one arm.

    ``lower``, ``upper``: joint limits (n,), may be +-inf (continuous joints)
    or very large; ``is_valid(Q)``: vectorised validity, ``(N, n)`` ->
    bool ``(N,)`` (True = collision-free); ``resolution``: max joint step (rad,
    max-norm) between checked samples of a segment; ``max_step``: if given,
    :meth:`plan` returns its path densified with :func:`interpolate` to at most
    this step per joint.

    Keyword options: ``margin`` (rad): OMPL samples joint j in
    ``[lower_j, upper_j]`` intersected with ``[min(start_j, goal_j) - margin,
    max(start_j, goal_j) + margin]``, which keeps the sampling box finite for
    unlimited joints (default pi: every angle modulo 2 pi is inside);
    ``planner_range``: RRTConnect's extension length (rad, Euclidean; None =
    OMPL's default, 20% of the box diagonal); ``shortcuts``: attempts of
    random (full or joint-subset) shortcuts after OMPL's own simplification,
    each one batched check (0 = only greedy waypoint removal); ``seed``: seed of OMPL's random
    generator, set before every OMPL plan, for reproducible plans (OMPL's seed
    is process-wide); ``log_level``: OMPL's log level (see
    :func:`set_ompl_log_level`; None leaves it alone).

    After :meth:`plan`, ``last_stats`` holds ``{"ompl": used OMPL,
    "time": seconds, "state_checks": ..., "motion_checks": ..., "status": ...}``.
    """

    def __init__(self, lower, upper, is_valid, resolution=0.01, max_step=None, *,
                 margin=math.pi, planner_range=None, shortcuts=100, seed=None, log_level="warn"):
        lo = np.atleast_1d(np.asarray(lower, float))
        hi = np.atleast_1d(np.asarray(upper, float))
        if lo.ndim != 1 or lo.shape != hi.shape or len(lo) == 0:
            raise ValueError("lower and upper must be (n,) arrays of the same length, got %s and %s"
                             % (lo.shape, hi.shape))
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo >= hi):
            raise ValueError("joint limits need lower < upper: lower %s, upper %s" % (lo, hi))
        if not callable(is_valid):
            raise TypeError("is_valid must be callable: (N, n) joint vectors -> bool mask (N,)")
        if not (resolution > 0 and math.isfinite(resolution)):
            raise ValueError("resolution must be finite and > 0, got %r" % (resolution,))
        if max_step is not None and not max_step > 0:
            raise ValueError("max_step must be > 0 or None, got %r" % (max_step,))
        if not (margin > 0 and math.isfinite(margin)):
            raise ValueError("margin must be finite and > 0, got %r" % (margin,))
        self.lower, self.upper, self.is_valid = lo, hi, is_valid
        self.resolution, self.max_step = float(resolution), max_step
        self.margin, self.planner_range, self.seed = float(margin), planner_range, seed
        self.log_level, self.shortcuts = log_level, int(shortcuts)
        self.last_stats = {}

    @property
    def dof(self):
        return len(self.lower)

    # -- batched checks ---------------------------------------------------
    def within_limits(self, Q, tol=1e-9):
        """Bool mask (N,): rows of ``Q`` (N, n) inside the joint limits."""
        Q = np.asarray(Q, float)
        return np.all((Q >= self.lower - tol) & (Q <= self.upper + tol) & np.isfinite(Q), axis=-1)

    def valid(self, Q):
        """Bool mask (N,): rows of ``Q`` (N, n) inside the limits and valid
        according to ``is_valid`` (one call, with only the in-limit rows)."""
        Q = np.asarray(Q, float).reshape(-1, self.dof)
        ok = self.within_limits(Q)
        if ok.any():
            sub = Q if ok.all() else Q[ok]
            res = np.asarray(self.is_valid(sub), dtype=bool)
            if res.shape != (len(sub),):
                raise ValueError("is_valid returned shape %s for %d joint vectors; expected (%d,)"
                                 % (res.shape, len(sub), len(sub)))
            ok[ok] = res
        return ok

    def segment_points(self, q0, q1):
        """Samples of the straight joint segment ``q0`` -> ``q1``, both ends
        included, at most ``resolution`` apart per joint."""
        return _densify(np.array([q0, q1], float).reshape(2, self.dof), self.resolution)[0]

    def segment_clear(self, q0, q1):
        """True if the straight joint segment ``q0`` -> ``q1`` is inside the
        limits and valid at every sample (one batched ``is_valid`` call)."""
        return bool(self.valid(self.segment_points(q0, q1)).all())

    def path_clear(self, path):
        """True if every segment of ``path`` (M, n) is clear (one batched call)."""
        P = np.asarray(path, float).reshape(-1, self.dof)
        return bool(self.valid(_densify(P, self.resolution)[0]).all())

    def first_blocked(self, path):
        """Index of the first segment of ``path`` with an invalid sample
        (``len(path) - 1`` if only the last waypoint is invalid), or None."""
        P = np.asarray(path, float).reshape(-1, self.dof)
        Q, seg = _densify(P, self.resolution)
        bad = np.flatnonzero(~self.valid(Q))
        return None if len(bad) == 0 else int(seg[bad[0]])

    # -- planning ---------------------------------------------------------
    def _check_end(self, q, which, q_start, q_goal):
        if not self.within_limits(q[None])[0]:
            j = int(np.flatnonzero(~((q >= self.lower - 1e-9) & (q <= self.upper + 1e-9)))[0]) \
                if np.all(np.isfinite(q)) else int(np.flatnonzero(~np.isfinite(q))[0])
            raise PlanningError(
                "%s_limits" % which,
                "%s configuration %s is outside the joint limits: joint %d = %.4g not in [%.4g, %.4g]"
                % (which, _fmt(q), j, q[j], self.lower[j], self.upper[j]), q_start, q_goal)
        if not self.valid(q[None])[0]:
            raise PlanningError("%s_invalid" % which, "%s configuration %s is in collision (is_valid is False)"
                                % (which, _fmt(q)), q_start, q_goal)

    def plan(self, q_start, q_goal, timeout=1.0, simplify=True, seed=None):
        """A collision-free path ``(M, n)`` from ``q_start`` to ``q_goal``
        (first and last rows are exactly those).  The straight segment is
        returned as ``[start, goal]`` when clear; otherwise RRTConnect plans
        for at most ``timeout`` s and the result is shortcut (``simplify``;
        bounded work, not counted in ``timeout``).
        Every returned path passes :meth:`path_clear`.  ``seed`` overrides the
        planner's seed for this call.  Raises :class:`PlanningError`."""
        t0 = time.perf_counter()
        qs = np.asarray(q_start, float).reshape(-1)
        qg = np.asarray(q_goal, float).reshape(-1)
        for q, name in ((qs, "q_start"), (qg, "q_goal")):
            if q.shape != (self.dof,):
                raise ValueError("%s must have %d joints, got %d" % (name, self.dof, q.size))
        self._check_end(qs, "start", qs, qg)
        self._check_end(qg, "goal", qs, qg)
        self.last_stats = {"ompl": False, "status": "straight", "state_checks": 0, "motion_checks": 0}
        path = np.array([qs, qg])
        if not self.segment_clear(qs, qg):
            paths, stats = self._ompl_plan(qs, qg, float(timeout), simplify,
                                           self.seed if seed is None else seed)
            self.last_stats.update(stats)
            if paths is None:
                raise PlanningError(
                    "no_path", "no collision-free path from start %s to goal %s found within %.3g s "
                    "(RRTConnect: %s)" % (_fmt(qs), _fmt(qg), timeout, stats["status"]), qs, qg)
            # candidates, best first: OMPL-simplified + our shortcuts, the raw
            # RRTConnect path + our shortcuts, the raw path as OMPL checked it; the
            # first that passes the final batched check wins (a sub-segment's
            # samples differ from the segment's, so a shortcut of a path that
            # grazes an obstacle can in rare cases fail the final check)
            candidates = [(p, simplify) for p in paths] + ([(paths[-1], False)] if simplify else [])
            for path, shortcut in candidates:
                path = _dedupe(path)
                path[0], path[-1] = qs, qg
                if shortcut:
                    path = self._shortcut(path, self.seed if seed is None else seed)
                if self.path_clear(path):
                    break
            else:
                raise PlanningError("path_invalid", "every path planned from %s to %s failed the final "
                                    "check at resolution %g" % (_fmt(qs), _fmt(qg), self.resolution), qs, qg)
        if self.max_step is not None:
            path = interpolate(path, self.max_step)
        self.last_stats["time"] = time.perf_counter() - t0
        return path

    def _shortcut(self, path, seed):
        """Deterministic shortcutting with batched segment checks: random
        shortcuts between two points anywhere on the path (``shortcuts``
        attempts, numpy RNG seeded with ``seed``), then greedy vertex removal
        (from each kept waypoint jump to the farthest waypoint it sees)."""
        rng = np.random.default_rng(None if seed is None else int(seed))
        P = path
        for _ in range(self.shortcuts):
            seg_len = np.abs(np.diff(P, axis=0)).max(axis=1)
            cum = np.concatenate([[0.0], np.cumsum(seg_len)])
            if len(P) < 3 or cum[-1] <= 0:
                break
            t1, t2 = np.sort(rng.uniform(0.0, cum[-1], 2))
            i1 = min(int(np.searchsorted(cum, t1, "right")) - 1, len(P) - 2)
            i2 = min(int(np.searchsorted(cum, t2, "right")) - 1, len(P) - 2)
            if i1 == i2:
                continue
            a = P[i1] + (P[i1 + 1] - P[i1]) * ((t1 - cum[i1]) / max(seg_len[i1], 1e-300))
            b = P[i2] + (P[i2 + 1] - P[i2]) * ((t2 - cum[i2]) / max(seg_len[i2], 1e-300))
            if rng.random() < 0.5:   # full shortcut a -> b
                mid = np.array([a, b])
            else:   # partial: a random subset of joints goes straight, the others follow the path
                joints = rng.random(self.dof) < 0.5
                if not joints.any() or joints.all():
                    continue
                mid = np.vstack([a, P[i1 + 1:i2 + 1], b])
                s = np.concatenate([[t1], cum[i1 + 1:i2 + 1], [t2]])
                w = (s - t1) / (t2 - t1)
                mid[:, joints] = a[joints] + (b - a)[joints] * w[:, None]
            piece = np.vstack([P[i1], mid, P[i2 + 1]])
            if self.path_clear(piece):   # exactly the new segments, as path_clear will see them
                P = _dedupe(np.vstack([P[:i1], piece, P[i2 + 2:]]))
        keep, i, M = [0], 0, len(P)
        while i < M - 1:
            j = M - 1
            while j > i + 1 and not self.segment_clear(P[i], P[j]):
                j -= 1
            keep.append(j)
            i = j
        return P[keep]

    def _ompl_plan(self, qs, qg, timeout, simplify, seed):
        """RRTConnect (+ OMPL shortcutting).  Returns ``(path or None, stats)``;
        every OMPL object is released before returning."""
        ob, og, ou = _ompl()
        if self.log_level is not None:
            set_ompl_log_level(self.log_level)
        if seed is not None:
            # OMPL logs an error when reseeding after its first RNG exists; the
            # new seed still applies to every RNG created afterwards.
            level = ou.getLogLevel()
            ou.setLogLevel(ou.LOG_NONE)
            ou.RNG.setSeed(int(seed))
            ou.setLogLevel(level)
        n = self.dof
        lo = np.maximum(self.lower, np.minimum(qs, qg) - self.margin)
        hi = np.minimum(self.upper, np.maximum(qs, qg) + self.margin)
        cb = _Callbacks(self, time.monotonic() + timeout)
        result, status = None, "not run"
        space = bounds = ss = si = mv = planner = start = goal = ptc = pathg = psk = None
        try:
            space = ob.RealVectorStateSpace(n)
            bounds = ob.RealVectorBounds(n)
            for j in range(n):
                bounds.setLow(j, float(lo[j]))
                bounds.setHigh(j, float(hi[j]))
            space.setBounds(bounds)
            ss = og.SimpleSetup(space)
            ss.setStateValidityChecker(cb.state)
            si = ss.getSpaceInformation()
            mv = _motion_validator_class()(si, cb.motion)
            si.setMotionValidator(mv)
            start, goal = si.allocState(), si.allocState()
            start[0:n] = [float(v) for v in qs]
            goal[0:n] = [float(v) for v in qg]
            ss.setStartAndGoalStates(start, goal)
            planner = og.RRTConnect(si)
            if self.planner_range is not None:
                planner.setRange(float(self.planner_range))
            ss.setPlanner(planner)
            ptc = ob.PlannerTerminationCondition(cb.stop)
            st = ss.solve(ptc)
            status = st.asString()
            if cb.error is None and ss.haveExactSolutionPath():
                pathg = ss.getSolutionPath()
                result = [np.array([s[0:n] for s in pathg.getStates()], float)]
                if simplify and pathg.getStateCount() > 2:
                    psk = og.PathSimplifier(si)
                    psk.reduceVertices(pathg)
                    psk.partialShortcutPath(pathg)
                    psk.reduceVertices(pathg)
                    result.insert(0, np.array([s[0:n] for s in pathg.getStates()], float))
        finally:
            space = bounds = ss = si = mv = planner = start = goal = ptc = pathg = psk = st = None
            exc = cb.release()
        stats = {"ompl": True, "status": status, "state_checks": cb.states, "motion_checks": cb.motions}
        if exc is not None:
            raise exc
        return result, stats
