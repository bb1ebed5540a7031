"""Joint-space planning (ambots.planning): straight-segment shortcut, OMPL
RRTConnect fallback on toy problems with a wall in joint space that has a gap,
batched validity checks, typed errors, interpolation, time parametrisation,
and a clean interpreter exit (no nanobind leak reports from OMPL)."""
import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from ambots.errors import AmbotsError
from ambots.planning import JointPlanner, PlanningError, interpolate, time_parametrize

RES = 0.01
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def wall(gap_center, gap_half=0.3, half=0.2, inflate=0.0, gap_dims=(1,)):
    """Vectorised validity: joint 0 in (-half, half) is a wall, except a gap
    where the joints ``gap_dims`` are within ``gap_half`` of ``gap_center``.
    ``inflate`` grows the obstacle in the max-norm (planner side): a segment
    sampled at spacing ``2 * inflate`` that passes the inflated check cannot
    touch the true obstacle anywhere between samples."""
    dims = list(gap_dims)

    def is_valid(Q):
        Q = np.asarray(Q, float)
        assert Q.ndim == 2
        in_wall = np.abs(Q[:, 0]) < half + inflate
        in_gap = np.all(np.abs(Q[:, dims] - gap_center) < gap_half - inflate, axis=1)
        return ~(in_wall & ~in_gap)
    return is_valid


class Counting:
    """Wraps an is_valid function and records the batch sizes it is called with."""

    def __init__(self, fn):
        self.fn, self.batches = fn, []

    def __call__(self, Q):
        self.batches.append(len(Q))
        return self.fn(Q)


def assert_path_ok(P, q0, q1, lower, upper, truth):
    P = np.asarray(P)
    assert P.ndim == 2 and P.shape[1] == len(q0) and len(P) >= 2
    np.testing.assert_array_equal(P[0], q0)
    np.testing.assert_array_equal(P[-1], q1)
    assert np.all(np.isfinite(P))
    dense = interpolate(P, 1e-3)
    assert np.all(dense >= lower) and np.all(dense <= upper), "path leaves the joint limits"
    bad = ~truth(dense)
    assert not bad.any(), "path hits the obstacle at %s" % dense[bad][:3]


# -- 2-D -------------------------------------------------------------------

LO2, HI2 = np.array([-3.0, -3.0]), np.array([3.0, 3.0])
A2, B2 = np.array([-1.0, 0.0]), np.array([1.0, 0.0])


def planner2(**kw):
    return JointPlanner(LO2, HI2, wall(1.5, inflate=RES / 2), resolution=RES, seed=7, **kw)


def test_straight_segment_refused_when_blocked_and_planned_path_goes_through_gap():
    p = planner2()
    assert not p.segment_clear(A2, B2)
    assert not p.path_clear([A2, B2])
    P = p.plan(A2, B2)
    assert p.last_stats["ompl"] and p.last_stats["motion_checks"] > 0
    assert len(P) >= 3
    assert_path_ok(P, A2, B2, LO2, HI2, wall(1.5))
    dense = interpolate(P, 1e-3)
    crossing = dense[np.abs(dense[:, 0]) < 0.2]
    assert len(crossing) and np.all(np.abs(crossing[:, 1] - 1.5) < 0.3)
    assert p.path_clear(P)


def test_first_blocked_names_the_segment():
    p = planner2()
    path = [A2, [-1.0, 1.5], [1.0, 1.5], B2]
    assert p.first_blocked(path) is None
    assert p.first_blocked([A2, [-0.5, 0.0], B2]) == 1


def test_clear_straight_segment_returns_two_waypoints_without_ompl(monkeypatch):
    def no_ompl(*a, **k):
        raise AssertionError("OMPL must not be called for a clear straight segment")
    monkeypatch.setattr(JointPlanner, "_ompl_plan", no_ompl)
    p = planner2()
    q0, q1 = np.array([0.5, -1.0]), np.array([2.5, 2.0])
    P = p.plan(q0, q1)
    assert P.shape == (2, 2)
    np.testing.assert_array_equal(P, [q0, q1])
    assert p.last_stats["ompl"] is False
    with pytest.raises(AssertionError):   # and the blocked case does go to OMPL
        p.plan(A2, B2)


def test_segment_and_path_checks_are_one_batched_call_at_resolution():
    fn = Counting(wall(1.5))
    p = JointPlanner(LO2, HI2, fn, resolution=RES)
    q0, q1 = np.array([0.5, -2.0]), np.array([2.5, 2.0])
    assert p.segment_clear(q0, q1)
    assert len(fn.batches) == 1 and fn.batches[0] >= 4.0 / RES
    pts = p.segment_points(q0, q1)
    assert np.abs(np.diff(pts, axis=0)).max() <= RES + 1e-12
    np.testing.assert_array_equal(pts[[0, -1]], [q0, q1])
    fn.batches.clear()
    assert p.path_clear([q0, q1, [0.5, 2.0], [2.9, 2.9]])
    assert len(fn.batches) == 1
    # a thin obstacle (1.5 x resolution wide) across the segment is found
    thin = JointPlanner(LO2, HI2, lambda Q: ~(np.abs(Q[:, 0] - 1.234) < 0.75 * RES), resolution=RES)
    assert not thin.segment_clear(q0, q1)
    # the joint limits are part of the check
    assert not p.segment_clear([0.5, 0.0], [3.5, 0.0])


def test_seed_makes_plans_reproducible():
    P1, P2 = planner2().plan(A2, B2), planner2().plan(A2, B2)
    np.testing.assert_array_equal(P1, P2)


def test_unsimplified_path_is_valid_and_simplified_is_not_longer():
    p = planner2()
    raw, short = p.plan(A2, B2, simplify=False), p.plan(A2, B2)
    assert_path_ok(raw, A2, B2, LO2, HI2, wall(1.5))
    length = lambda P: np.linalg.norm(np.diff(P, axis=0), axis=1).sum()  # noqa: E731
    assert length(short) <= length(raw) + 1e-9


def test_max_step_densifies_the_returned_path():
    p = planner2(max_step=0.05)
    P = p.plan(A2, B2)
    assert np.abs(np.diff(P, axis=0)).max() <= 0.05 + 1e-12
    assert_path_ok(P, A2, B2, LO2, HI2, wall(1.5))
    assert p.plan([0.5, 0.0], [1.0, 0.0]).shape == (11, 2)


# -- errors ------------------------------------------------------------------

def test_start_in_collision_is_a_planning_error_naming_the_start():
    p = planner2()
    with pytest.raises(PlanningError) as e:
        p.plan([0.0, 0.123456], B2)
    assert isinstance(e.value, AmbotsError) and e.value.reason == "start_invalid"
    assert "start configuration [0, 0.1235] is in collision" in str(e.value)
    np.testing.assert_array_equal(e.value.q_start, [0.0, 0.123456])


def test_goal_in_collision_is_a_planning_error_naming_the_goal():
    with pytest.raises(PlanningError, match=r"goal configuration \[0.1, -2\] is in collision") as e:
        planner2().plan(A2, [0.1, -2.0])
    assert e.value.reason == "goal_invalid"


def test_start_or_goal_outside_limits_names_the_joint():
    with pytest.raises(PlanningError, match=r"start configuration \[-1, 3.5\] is outside the joint "
                                            r"limits: joint 1 = 3.5 not in \[-3, 3\]") as e:
        planner2().plan([-1.0, 3.5], B2)
    assert e.value.reason == "start_limits"
    with pytest.raises(PlanningError, match="goal configuration .* outside the joint limits: joint 0 = nan"):
        planner2().plan(A2, [np.nan, 0.0])


def test_no_path_within_timeout():
    closed = wall(1.5, gap_half=0.0)   # a wall without a gap
    p = JointPlanner(LO2, HI2, closed, seed=1)
    t = time.perf_counter()
    with pytest.raises(PlanningError, match=r"no collision-free path from start \[-1, 0\] to goal \[1, 0\] "
                                            r"found within 0.2 s") as e:
        p.plan(A2, B2, timeout=0.2)
    assert e.value.reason == "no_path"
    assert time.perf_counter() - t < 1.5


def test_errors_of_is_valid_propagate_out_of_ompl():
    calls = []

    def broken(Q):
        calls.append(len(Q))
        if len(calls) > 3:
            raise RuntimeError("checker broke")
        return wall(1.5)(Q)
    with pytest.raises(RuntimeError, match="checker broke"):
        JointPlanner(LO2, HI2, broken).plan(A2, B2)
    with pytest.raises(ValueError, match="is_valid returned shape"):
        JointPlanner(LO2, HI2, lambda Q: True).segment_clear(A2, B2)


def test_bad_arguments():
    with pytest.raises(ValueError):
        JointPlanner([0, 1], [1, 0], wall(1.5))
    with pytest.raises(ValueError):
        JointPlanner(LO2, HI2, wall(1.5), resolution=0)
    with pytest.raises(ValueError, match="q_goal must have 2 joints"):
        planner2().plan(A2, [1, 2, 3])


# -- 6-D -------------------------------------------------------------------

N6 = 6
LO6, HI6 = -2 * np.pi * np.ones(N6), 2 * np.pi * np.ones(N6)   # UR10-like
A6 = np.array([-1.0, 0.0, 0.0, 0.5, 0.0, 0.0])
B6 = np.array([1.0, 0.0, 0.0, -0.5, 0.3, 0.0])


def wall6(inflate=0.0):
    return wall(1.0, gap_half=0.35, inflate=inflate, gap_dims=(1, 2))


@pytest.mark.parametrize("seed", [1, 2])
def test_6d_wall_with_gap(seed):
    p = JointPlanner(LO6, HI6, wall6(RES / 2), resolution=RES, seed=seed)
    assert not p.segment_clear(A6, B6)
    P = p.plan(A6, B6, timeout=5.0)
    assert p.last_stats["ompl"]
    assert_path_ok(P, A6, B6, LO6, HI6, wall6())


def test_6d_unlimited_joints():
    lo, hi = np.full(N6, -np.inf), np.full(N6, np.inf)
    lo[0], hi[0] = -1e9, 1e9   # "very large" works too
    p = JointPlanner(lo, hi, wall6(RES / 2), resolution=RES, seed=3)
    P = p.plan(A6, B6, timeout=5.0)
    assert_path_ok(P, A6, B6, lo, hi, wall6())
    # the sampling box stays within margin (pi) of the start/goal box
    assert np.all(P >= np.minimum(A6, B6) - np.pi - 1e-9) and np.all(P <= np.maximum(A6, B6) + np.pi + 1e-9)


# -- interpolate / time_parametrize -------------------------------------------

def test_interpolate_keeps_waypoints_and_bounds_the_step():
    P = np.array([[0.0, 0.0], [1.0, 0.1], [1.0, 0.1], [0.2, -0.5]])
    Q = interpolate(P, 0.07)
    assert np.abs(np.diff(Q, axis=0)).max() <= 0.07 + 1e-12
    for w in P:
        assert np.any(np.all(Q == w, axis=1))
    np.testing.assert_array_equal(Q[[0, -1]], P[[0, -1]])
    assert len(interpolate(P[:1], 0.1)) == 1
    with pytest.raises(ValueError):
        interpolate(P, 0.0)


def test_time_parametrize_respects_vmax():
    rng = np.random.default_rng(0)
    P = np.cumsum(rng.uniform(-1, 1, (20, 6)), axis=0)
    vmax = np.array([2.0, 2.0, 3.0, 3.0, 3.0, 3.0])
    t = time_parametrize(P, vmax)
    assert t.shape == (20,) and t[0] == 0.0 and np.all(np.diff(t) > 0)
    v = np.abs(np.diff(P, axis=0)) / np.diff(t)[:, None]
    assert np.all(v <= vmax * (1 + 1e-9))
    # time-optimal without acceleration limits: one joint at its limit on every segment
    np.testing.assert_allclose((v / vmax).max(axis=1), 1.0)


def test_time_parametrize_with_acceleration():
    vmax, amax = np.array([1.0, 2.0]), np.array([1.0, 1.0])
    # long move: accelerate to 1 rad/s (1 s, 0.5 rad), cruise 3 rad (3 s), brake (1 s)
    np.testing.assert_allclose(time_parametrize([[0, 0], [4, 0]], vmax, amax), [0, 5.0])
    # short move: triangle, never reaches vmax: 2 * sqrt(d / a)
    np.testing.assert_allclose(time_parametrize([[0, 0], [0.25, 0]], vmax, amax), [0, 1.0])
    # velocity binds on joint 0, acceleration on joint 1 (V = 1/3, A = 1/4): T = 1/V + V/A
    np.testing.assert_allclose(time_parametrize([[0, 0], [3, 4]], vmax, amax), [0, 3 + 4 / 3])
    # every segment takes at least as long as without the acceleration limit
    rng = np.random.default_rng(1)
    P = np.cumsum(rng.uniform(-1, 1, (15, 2)), axis=0)
    ta, tv = time_parametrize(P, vmax, amax), time_parametrize(P, vmax)
    assert np.all(np.diff(ta) >= np.diff(tv) - 1e-12) and np.all(np.diff(ta) > 0)
    # a repeated waypoint takes no time; bad limits are refused
    np.testing.assert_allclose(time_parametrize([[0, 0], [0, 0], [1, 0]], vmax, amax), [0, 0, 2.0])
    with pytest.raises(ValueError):
        time_parametrize(P, [1.0, 0.0])
    with pytest.raises(ValueError):
        time_parametrize(P, vmax, [1.0, np.inf])


# -- clean exit ----------------------------------------------------------------

def test_no_ompl_leak_warnings_at_exit():
    script = textwrap.dedent("""
        import numpy as np
        from ambots.planning import JointPlanner, PlanningError
        def is_valid(Q):
            return ~((np.abs(Q[:, 0]) < 0.2) & ~(np.abs(Q[:, 1] - 1.5) < 0.3))
        p = JointPlanner([-3, -3], [3, 3], is_valid, seed=5)
        P = p.plan([-1, 0], [1, 0])
        assert p.last_stats["ompl"] and len(P) >= 3, p.last_stats
        closed = JointPlanner([-3, -3], [3, 3], lambda Q: np.abs(Q[:, 0]) >= 0.2)
        try:
            closed.plan([-1, 0], [1, 0], timeout=0.05)
        except PlanningError:
            pass
        def broken(Q):
            raise RuntimeError("boom")
        p.is_valid = lambda Q: broken(Q) if len(Q) == 1 else is_valid(Q)
        try:
            p.plan([-1, 0], [1, 0])
        except RuntimeError:
            pass
        print("planned", len(P))
    """)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.path.join(ROOT, "src") + os.pathsep + env.get("PYTHONPATH", "")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env=env)
    assert r.returncode == 0, r.stderr
    assert "planned" in r.stdout
    for word in ("leak", "nanobind", "Warning", "Error"):
        assert word.lower() not in r.stderr.lower(), r.stderr
