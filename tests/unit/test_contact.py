"""Continuous contact check (ambots.contact), against brute force: motion
sampled every 0.1 ms, far denser than any sweep the check allows."""
import numpy as np
import pytest

from ambots.collision import ArmBody, clearance_between
from ambots.config import default_cell_path, load_cell
from ambots.contact import RESOLUTION_M, Sweep, scan, sweep_radii
from ambots.sim import check_traces


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def bodies(cell):
    return {a.name: ArmBody.from_arm(a) for a in cell.arms}


def _path_lengths(body, q0, q1, n=2000):
    """Path length of every capsule end and of the point of the rim that moves
    most (end + radius), along the straight joint-space line q0 -> q1."""
    Q = q0 + np.linspace(0.0, 1.0, n)[:, None] * (q1 - q0)
    A, B, r = body.capsules(Q)
    steps = lambda P: np.linalg.norm(np.diff(P, axis=0), axis=-1).sum(axis=0)
    return np.maximum(steps(A), steps(B))


def test_no_point_moves_farther_than_the_sweep_bound(cell, bodies):
    rng = np.random.default_rng(3)
    for arm in cell.arms:
        body, kin = bodies[arm.name], bodies[arm.name].kin
        R = sweep_radii(body)
        assert R.shape == (kin.dof,) and np.all(R > 0)
        lo, hi = np.maximum(kin.lower, -np.pi), np.minimum(kin.upper, np.pi)
        for _ in range(20):
            q0 = rng.uniform(lo, hi)
            q1 = q0 + rng.normal(0.0, 0.2, kin.dof)
            bound = np.abs(q1 - q0) @ R
            moved = _path_lengths(body, q0, q1)
            # the capsule ends move no farther than the bound; the rim adds at most r * rotation,
            # which the bound counts in each joint's radius
            assert moved.max() <= bound + 1e-9, (arm.name, moved.max(), bound)


def test_one_joint_alone_reaches_its_bound_within_a_factor_of_three(cell, bodies):
    """The bound is not wildly loose: turning only the base joint with the arm
    folded over the bed, the nozzle half the stretched length (reach and
    print head) from the base axis and 0.1 m up, the farthest point moves at
    least a third as far as the bound says."""
    for arm in cell.arms:
        body = bodies[arm.name]
        half = (arm.profile.reach + np.linalg.norm(arm.profile.tool_xyz)) / 2.0
        q0 = body.kin.ik([half, 0.0, 0.1], np.asarray(arm.profile.home, dtype=float))
        q1 = q0.copy()
        q1[0] += 0.3
        assert _path_lengths(body, q0, q1).max() >= sweep_radii(body)[0] * 0.3 / 3


def test_scan_finds_a_dip_between_coarse_samples():
    """A point passing 1 mm through an obstacle in 20 ms, between two samples of
    a 0.1 s grid: the scan finds it, and its bound is below the true minimum."""
    v = 0.5                                            # m/s past the obstacle at t = 3.05 s
    clearance = lambda t: np.abs(v * (t - 3.05)) - 0.001
    s = scan(clearance, lambda t0, t1: v * (t1 - t0), 10.0, track_min=False)
    assert s.contacts > 0 and s.min < 0 and s.bound <= -0.001
    grid = np.arange(0.0, 10.0, 0.1)
    assert clearance(grid).min() > 0                   # what a 0.1 s grid saw


def test_scan_bound_brackets_the_true_minimum():
    rng = np.random.default_rng(5)
    for _ in range(10):
        t0, depth, v = rng.uniform(1, 9), rng.uniform(0.003, 0.05), rng.uniform(0.01, 1.0)
        clearance = lambda t: np.abs(v * (t - t0)) + depth
        s = scan(clearance, lambda a, b: v * (b - a), 10.0)
        assert s.contacts == 0
        assert s.bound <= depth + 1e-12 <= s.min + 1e-12
        assert s.min - depth <= RESOLUTION_M / 2 + 1e-9       # resolution reached near the minimum


def _down(cell, arm, body, points):
    """Nozzle-down joint vectors for world points (M, 3), by IK from home."""
    from ambots.workspace import down_in_base, world_to_base
    Q, ok, _ = body.kin.ik_batch(world_to_base(arm, np.asarray(points, dtype=float)),
                                 np.asarray(arm.profile.home, dtype=float), down_in_base(arm))
    assert ok.all()
    return Q


def test_arms_swinging_through_each_other_between_samples_are_caught(cell, bodies):
    """The UR10 nozzle sweeps across the Kinova's, from 200 mm on one side to
    300 mm on the other, in 0.06 s: at 0.1 s samples the poses are clear;
    brute force at 0.1 ms and the continuous check both see the contact.
    (On the +y side the UR10's wrist 1 housing, 76 mm in radius around the
    J4 axis, which runs 115 mm sideways from the wrist towards -y, reaches
    back over the Kinova's head: it clears it only from about 250 mm.)"""
    kin, ur = cell.arm("kinova"), cell.arm("ur10")
    x, z = cell.bed.pose[0, 3], cell.bed.pose[2, 3] + 0.05
    qk = _down(cell, kin, bodies["kinova"], [[x, 0.0, z]])[0]
    qa, qb = _down(cell, ur, bodies["ur10"], [[x, -0.2, z], [x, 0.3, z]])
    t = np.array([0.0, 10.03, 10.09, 20.0])
    Qk, Qu = np.tile(qk, (4, 1)), np.array([qa, qa, qb, qb])
    traces = {"kinova": (t, Qk), "ur10": (t, Qu)}
    at = lambda Q, times: Sweep(t, Q, np.zeros(6)).at(times)
    dense = np.arange(0.0, 20.0, 1e-4)
    brute = clearance_between(bodies["kinova"], at(Qk, dense), bodies["ur10"], at(Qu, dense))
    coarse = np.arange(0.0, 20.0, 0.1)
    sparse = clearance_between(bodies["kinova"], at(Qk, coarse), bodies["ur10"], at(Qu, coarse))
    assert brute.min() < 0 < sparse.min(), (brute.min(), sparse.min())
    out = check_traces(traces, {a.name: a for a in cell.arms}, cell)
    assert out["collisions"]["arm_arm"] > 0
    assert out["bound_mm"]["arm_arm"] <= brute.min() * 1000 + 1e-6
    assert abs(out["min_clearance_mm"] - brute.min() * 1000) < RESOLUTION_M * 1000


def test_clear_motion_has_a_positive_bound_below_the_brute_force_minimum(cell, bodies):
    kin, ur = cell.arm("kinova"), cell.arm("ur10")
    qk = np.asarray(kin.profile.home, dtype=float)
    qu = np.asarray(ur.profile.home, dtype=float)
    t = np.array([0.0, 5.0, 6.0, 12.0])
    Qk = np.array([qk, qk + [0.2, 0.1, 0, 0, 0, 0.5], qk - [0.2, 0, 0.1, 0, 0, 0], qk])
    Qu = np.array([qu, qu - [0.2, 0, 0, 0.1, 0, 0], qu + [0.1, 0, 0, 0, 0, 0], qu])
    out = check_traces({"kinova": (t, Qk), "ur10": (t, Qu)}, {a.name: a for a in cell.arms}, cell)
    dense = np.arange(0.0, 12.0, 1e-3)
    brute = clearance_between(bodies["kinova"], Sweep(t, Qk, np.zeros(6)).at(dense),
                              bodies["ur10"], Sweep(t, Qu, np.zeros(6)).at(dense)).min() * 1000
    assert out["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    assert 0 < out["bound_mm"]["arm_arm"] <= brute <= out["min_clearance_mm"] + 1e-9
    assert out["min_clearance_mm"] - brute < RESOLUTION_M * 1000
