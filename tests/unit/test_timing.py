"""Timing robustness of the concurrent schedules, executed by the firmware
itself (``ambots.sim``: every arm's ArmRunner on one simulated clock) with
each arm's speed perturbed at random, block by block (every run of G-code
moves between two directives, every park move stretched by its own factor
in [lo, hi], ranges drawn per arm): two arms facing each other (banded
sweeps), three around a point, four in the corners and four in a row on
alternate sides of a beam (scheduled timeline: the middle arms of the row
cannot keep clear of both their seams' zones at once, as banded sweeps
need).  However the timing slips, the barriers absorb it: no arm-arm
contact, and every two adjacent arms keep their nozzles the pair's seam zone
apart across the plane between them.

The arms' clocks are independent (as at ``speed max`` live): an arm that
reaches a barrier whose report is already there, made by an arm whose
clock is ahead, waits until the report's time; passing at once let the
arm into the band its neighbour left only later (83.8 mm across a 90.1 mm
zone, the fault suite's contacts)."""
import numpy as np
import pytest
import trimesh

from ambots import data_path
from ambots.config import default_cell_path, load_cell
from ambots.coordinate import read_sliced, adjacent_arms, seam_planes, seam_zones_for
from ambots.job import run_job
from ambots.model import arm_kinematics
from ambots.contact import Sweep
from ambots.sim import _trace, check_motion, simulate

#: cell, model box (mm), arms (None: the cell's): small jobs of a few layers, wide enough
#: that two arms print at once beyond their seam zones (the arms' real envelopes: 154 mm
#: between the Kinova and the UR10, up to 240 mm with the Panda; a 160 mm block would lie
#: wholly in the zone, and the arms take turns)
LAYOUTS = {
    "two_arms": (None, (240.0, 40.0, 1.2), None),
    "three_arms": ("config/cells/three_arms.yaml", (240.0, 120.0, 0.6), None),
    "four_arms": ("config/cells/four_arms.yaml", (140.0, 120.0, 0.4), None),
    "beam_row": ("config/cells/eight_arms_beam.yaml", (1300.0, 20.0, 0.4),   # four in a row, alternate sides
                 ["kinova_3", "ur10_4", "ur10_5", "kinova_6"]),
}
SEEDS = {"two_arms": (0, 1, 2), "three_arms": (0,), "four_arms": (0,), "beam_row": (0,)}


@pytest.fixture(scope="module")
def jobs(tmp_path_factory):
    out = {}
    for key, (path, dims, names) in LAYOUTS.items():
        cell = load_cell(data_path(*path.split("/")) if path else default_cell_path())
        box = trimesh.creation.box(dims)
        box.apply_translation((0.0, 0.0, dims[2] / 2))
        model = str(tmp_path_factory.mktemp("models") / ("%s.stl" % key))
        box.export(model)
        out[key] = (cell, run_job(model, cell, [cell.arm(n) for n in names] if names else list(cell.arms)))
    return out


def nozzle_slack(result, cell, job, step_s=0.1):
    """For every two adjacent arms: the smallest (sum of the two nozzles'
    distances to the plane between them - the pair's zone), mm, over the
    executed motion sampled every ``step_s`` simulated seconds (the
    executed Hermite motion, as the collision check evaluates it),
    while both nozzles are at most at the printable height: the rule is
    about arms working on the part; home and park poses (and the moves
    between them and the part) are above it, out of the rule, and covered
    by the collision check."""
    parts = [p for p in job.parts if p.arm.name in job.programs]
    arms = [p.arm for p in parts]
    planes = seam_planes(parts)
    zones = seam_zones_for(cell, arms, parts)
    read = {a.name: read_sliced(job.sliced[a.name], a.name) for a in arms}
    adjacent = adjacent_arms(arms, read, planes, zones)
    traces = {n: _trace(r) for n, r in result.runners.items()}
    grid = np.arange(0.0, max(float(tr[0][-1]) for tr in traces.values()) + step_s, step_s)
    inv = np.linalg.inv(cell.bed.pose)
    nozzle = {}
    for name, r in result.runners.items():
        t, Q, V = traces[name]
        T = arm_kinematics(r.arm).fk_batch(Sweep(t, Q, np.zeros(Q.shape[1]), V).at(grid))
        world = T[:, :3, 3] @ r.arm.base_pose[:3, :3].T + r.arm.base_pose[:3, 3]
        nozzle[name] = (world @ inv[:3, :3].T + inv[:3, 3]) * 1000.0
    top = cell.bed.max_height * 1000.0
    out = {}
    for a in adjacent:
        for b in adjacent[a]:
            if a < b:
                (na, oa), (nb, ob) = planes[a, b], planes[b, a]
                low = (nozzle[a][:, 2] <= top) & (nozzle[b][:, 2] <= top)
                if low.any():
                    s = nozzle[a][low] @ na - oa + nozzle[b][low] @ nb - ob - zones[a, b]
                    inside = np.flatnonzero(s < 0)
                    # where the pair is inside its zone: how far each nozzle is off its own program's path
                    off = [(float(-s[i]), off_path(job.programs[a], nozzle[a][low][i]),
                            off_path(job.programs[b], nozzle[b][low][i])) for i in inside]
                    out[a, b] = (float(np.min(s)), int(low.sum()), off)
    return out


def off_path(program, p):
    """Distance (mm) from the point ``p`` (bed frame, mm) to the nearest move
    of ``program`` (its G-code segments, travels included)."""
    from ambots.gcode import Segment
    segs = [e for e in program.parse() if type(e) is Segment and e.start != e.end]
    S = np.array([e.start for e in segs])
    d = np.array([e.end for e in segs]) - S
    f = np.clip(((p - S) * d).sum(1) / (d * d).sum(1), 0.0, 1.0)
    return float(np.min(np.linalg.norm(S + f[:, None] * d - p, axis=1)))


@pytest.mark.parametrize("layout,seed", [(k, s) for k in LAYOUTS for s in SEEDS[k]])
def test_perturbed_speeds_never_bring_two_arms_into_contact(jobs, layout, seed):
    cell, job = jobs[layout]
    rng = np.random.default_rng(seed)
    # each arm its own range: from up to 2.5 times faster to 3 times slower than planned
    slow = {name: (float(rng.uniform(0.4, 1.0)), float(rng.uniform(1.2, 3.0))) for name in job.programs}
    base = simulate(job.programs, cell)
    result = simulate(job.programs, cell, slow=slow, seed=seed)
    assert base.finished and result.finished, result.reason
    assert result.makespan_s != pytest.approx(base.makespan_s, rel=0.02)      # the timing did change
    motion = check_motion(result, cell)
    assert motion["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, motion
    assert motion["min_clearance_mm"] > 0
    slack = nozzle_slack(result, cell, job)
    # two adjacent arms worked on the part at the same time for a while
    assert slack and max(n for _, n, _ in slack.values()) > 1000, slack
    # the zones' rule, sampled every 0.1 s, holds on the programs' paths: the schedule puts
    # pieces (and the travels between them) up to the band edges, so two nozzles at their
    # edges at once are exactly a zone apart; the executed motion may stray from a programmed
    # line (the timed curve between the planner's waypoints), and where a pair is inside its
    # zone, it is by no more than the two nozzles' distances to their own programs' paths
    # (measured: travels 0.02-0.2 mm off their line in three_arms, seed 0; the zone's 10 mm
    # margin absorbs it, contacts above are 0).  0.05 mm: the nearest point of a path need not
    # be the point the arm was executing (measured up to 0.035 mm)
    for pair, (s, _, off) in slack.items():
        for inside, da, db in off:
            assert inside <= da + db + 0.05, "%s and %s: nozzles %.2f mm inside their zone, %.3f + %.3f mm " \
                "off their paths" % (pair + (inside, da, db))
        assert s >= -0.5, "%s and %s: nozzles %.2f mm inside their zone" % (pair + (-s,))
    # the same deposit as planned: every arm printed all of its program
    for name, r in result.runners.items():
        assert sum(float(b.e_mm.sum()) for b in r.beads) == pytest.approx(
            sum(float(b.e_mm.sum()) for b in base.runners[name].beads), abs=1e-6)
