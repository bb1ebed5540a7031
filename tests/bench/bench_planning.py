"""Joint-space planning (ambots.planning), measured in one run:

1. wall time per plan (median / max over seeds, ms) of the 6-D wall-with-gap
   problem of tests/unit/test_planning.py (straight segment blocked, so every
   plan runs OMPL RRTConnect + shortcutting), UR10-like limits of +-2 pi;
2. batched ``segment_clear`` (one ``is_valid`` call for the whole segment)
   against a per-state Python loop calling ``is_valid(q[None])`` for each
   sample of the same segment (what a plain OMPL state validity checker does),
   as states/s and a ratio, for the toy wall and for a UR10 check that puts
   every link frame above the bed (vectorised forward kinematics)."""
import time

import numpy as np

from ambots.planning import JointPlanner

N6 = 6
LO6, HI6 = -2 * np.pi * np.ones(N6), 2 * np.pi * np.ones(N6)
A6 = np.array([-1.0, 0.0, 0.0, 0.5, 0.0, 0.0])
B6 = np.array([1.0, 0.0, 0.0, -0.5, 0.3, 0.0])
RES = 0.01
SEEDS = range(1, 31)


def wall6(Q):
    """Joint 0 in (-0.2, 0.2) is a wall except where joints 1 and 2 are both
    within 0.35 of 1.0 (inflated by RES / 2 as in the unit test)."""
    in_wall = np.abs(Q[:, 0]) < 0.2 + RES / 2
    in_gap = np.all(np.abs(Q[:, 1:3] - 1.0) < 0.35 - RES / 2, axis=1)
    return ~(in_wall & ~in_gap)


def plan_times():
    ms, checks, lengths = [], [], []
    for seed in SEEDS:
        p = JointPlanner(LO6, HI6, wall6, resolution=RES, seed=seed)
        t = time.perf_counter()
        P = p.plan(A6, B6, timeout=5.0)
        ms.append((time.perf_counter() - t) * 1e3)
        checks.append(p.last_stats["motion_checks"] + p.last_stats["state_checks"])
        lengths.append(np.abs(np.diff(P, axis=0)).sum())
    return np.array(ms), np.array(checks), np.array(lengths)


def throughput(planner, q0, q1, repeat=5):
    """(batched states/s, loop states/s, samples) for one segment."""
    Q = planner.segment_points(q0, q1)
    best_b = best_l = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        ok_b = planner.segment_clear(q0, q1)
        best_b = min(best_b, time.perf_counter() - t)
        t = time.perf_counter()
        ok_l = all(bool(planner.is_valid(q[None])[0]) for q in Q)
        best_l = min(best_l, time.perf_counter() - t)
    assert ok_b and ok_l, "the benchmark segment must be clear (else the loop stops early)"
    return len(Q) / best_b, len(Q) / best_l, len(Q)


def ur10_check():
    from ambots.config import load_arm_profile
    from ambots.model import arm_kinematics
    prof = load_arm_profile("config/arms/ur10.yaml")
    kin = arm_kinematics(prof)

    def above_bed(Q):   # every link frame after the shoulder at least 5 cm above the base plane
        return np.all(kin.link_frames(Q)[:, 2:, 2, 3] > 0.05, axis=1)
    planner = JointPlanner(kin.lower, kin.upper, above_bed, resolution=RES)
    home = np.asarray(prof.home, float)
    return planner, home, home + np.array([1.5, 0.3, 0.2, -0.5, 0.5, 1.0])


def main():
    ms, checks, lengths = plan_times()
    print("plan 6-D wall with gap (%d seeds, RRTConnect + shortcuts): median %.1f ms, max %.1f ms per plan; "
          "median %d Python validity callbacks; median path length %.2f rad (straight: %.2f)"
          % (len(ms), np.median(ms), ms.max(), np.median(checks), np.median(lengths), np.abs(B6 - A6).sum()),
          flush=True)
    toy = JointPlanner(LO6, HI6, wall6, resolution=RES)
    for name, (planner, q0, q1) in (("toy wall", (toy, A6 + [2.0, 0, 0, 0, 0, 0], B6 + [2.0, 0, 0, 0, 0, 0])),
                                    ("UR10 link frames above bed", ur10_check())):
        b, loop, n = throughput(planner, q0, q1)
        print("segment_clear %-27s %4d samples: batched %.0f states/s, per-state loop %.0f states/s; "
              "ratio batched/loop = %.0fx" % (name, n, b, loop, b / loop), flush=True)


if __name__ == "__main__":
    main()
