"""A cell of three or four arms also plans every smaller group of its arms
(``ambots.job._group_plans``): on the demo's long thin block the four arms
in the corners have zones that cover its 40 mm width, and two of them
finish sooner.  Checked in the offline simulation, not by the planner's
estimate: the group chosen, executed with the cell's other arms standing
at home until its first program parks them (A7), finishes sooner than all
four arms executed, and no arm touches another, the bed or the part."""
import numpy as np
import pytest
import trimesh

from ambots import data_path
from ambots.config import load_cell
from ambots.job import TIE_SHARE, _groups, run_job
from ambots.coordinate import park_positions_mm
from ambots.sim import check_motion, simulate


@pytest.fixture(scope="module")
def four():
    return load_cell(data_path("config", "cells", "four_arms.yaml"))


def test_the_groups_are_every_smaller_set_of_two_or_more_arms(four):
    names = lambda groups: [tuple(a.name for a in g) for g in groups]     # noqa: E731
    k1, u1, k2, u2 = (a.name for a in four.arms)
    assert names(_groups(four.arms)) == [(k1, u1), (k1, k2), (k1, u2), (u1, k2), (u1, u2), (k2, u2),
                                         (k1, u1, k2), (k1, u1, u2), (k1, k2, u2), (u1, k2, u2)]
    assert names(_groups(four.arms[:3])) == [(k1, u1), (k1, k2), (u1, k2)]
    assert _groups(four.arms[:2]) == []
    beam = load_cell(data_path("config", "cells", "eight_arms_beam.yaml"))
    assert _groups(beam.arms) == []             # 246 groups: not made


@pytest.fixture(scope="module")
def jobs(four, tmp_path_factory):
    """The planner's choice for a 240 x 40 x 1.2 mm block on the four-arm
    cell, and the four arms given."""
    path = str(tmp_path_factory.mktemp("groups") / "block_240x40.stl")
    trimesh.creation.box((240.0, 40.0, 1.2)).apply_translation((0.0, 0.0, 0.6)).export(path)
    return run_job(path, four), run_job(path, four, list(four.arms))


def test_every_group_is_planned_and_the_fastest_is_chosen(four, jobs):
    job, _ = jobs
    seen = sorted(tuple(sorted(c.arms)) for c in job.candidates if c.seam_turn_deg == 0 and c.seam_offsets is None)
    want = sorted(tuple(sorted(a.name for a in g)) for g in _groups(four.arms) + [four.arms]
                  + [[a] for a in four.arms])
    assert seen == want
    timed = [c for c in job.candidates if c.makespan_s is not None]
    assert len(timed) >= len(want)
    chosen = job.chosen
    assert len(chosen.arms) == 2 and sorted(job.programs) == sorted(chosen.arms)
    fastest = min(c.makespan_s for c in timed)
    assert chosen.makespan_s <= fastest * (1.0 + TIE_SHARE)
    together = next(c for c in timed if len(c.arms) == 4)
    assert chosen.makespan_s * (1.0 + TIE_SHARE) < together.makespan_s
    # the idle arms are sent to their park positions at once, by the first program
    idle = [a for a in four.arms if a.name not in job.programs]
    park = park_positions_mm(four, four.arms)
    first = job.programs[chosen.arms[0]].lines
    opening = [ln for ln in first[:12] if ln.startswith(";@A7")]
    assert opening == [";@A7 R%d X%g Y%g Z%g" % ((a.id,) + tuple(round(float(v), 3) for v in park[a.name]))
                       for a in idle]


def test_the_group_chosen_finishes_sooner_executed_and_touches_nothing(four, jobs):
    job, forced = jobs
    idle = [a for a in four.arms if a.name not in job.programs]
    result = simulate(job.programs, four, idle=idle)
    assert result.finished, result.reason
    assert set(result.runners) == {a.name for a in four.arms}
    motion = check_motion(result, four)
    assert motion["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}
    assert motion["min_clearance_mm"] > 0
    # the idle arms went to their park positions and stayed there
    park = park_positions_mm(four, four.arms)
    for arm in idle:
        r = result.runners[arm.name]
        assert r.stats.first_motion_s is not None and not r.beads
        nozzle = np.asarray(r.nozzle_mm(), float)
        assert np.linalg.norm(nozzle - np.asarray(park[arm.name], float)) < 1.0, (arm.name, nozzle)
    # executed, the group is faster than the four arms executed
    all_four = simulate(forced.programs, four)
    assert all_four.finished, all_four.reason
    assert result.makespan_s * (1.0 + TIE_SHARE) < all_four.makespan_s


def test_the_fastest_pair_turns_its_seam_with_the_pace_of_its_own_busy_times(tmp_path, monkeypatch):
    """The pair that gets the seam variants (turned, stepped) splits them
    with each arm's pace from its own plan by volume, as the plan of all the
    cell's arms does, whether or not its split again was kept.  Here every
    split again is made slower by 1,000 s, so none is kept: before session
    34 a group's variants then got no pace at all.  The pace is found again
    from the pair's plan with the arms given (``--arms``: by volume, not split
    again): each arm's busy time over their mean, rounded."""
    import ambots.job
    from ambots.job import PACE_DIGITS
    three = load_cell(data_path("config", "cells", "three_arms.yaml"))
    path = str(tmp_path / "block_240x40.stl")
    trimesh.creation.box((240.0, 40.0, 1.2)).apply_translation((0.0, 0.0, 0.6)).export(path)
    real_cooperative, real_seams = ambots.job._cooperative, ambots.job._seam_plans
    calls = []

    def slower_again(job, cell, arms, seam, settings, reach, pace, *rest, **kw):
        plan = real_cooperative(job, cell, arms, seam, settings, reach, pace, *rest, **kw)
        if pace is None or len(rest) > 5:          # split by volume, or a seam variant: as it is
            return plan
        c = plan[3]
        return plan[:3] + (ambots.job.replace(c, makespan_s=c.makespan_s + 1000.0),)

    def spy(job, cell, arms, seam, settings, reach, pace, *rest):
        calls.append(([a.name for a in arms], pace))
        return real_seams(job, cell, arms, seam, settings, reach, pace, *rest)

    monkeypatch.setattr(ambots.job, "_cooperative", slower_again)
    monkeypatch.setattr(ambots.job, "_seam_plans", spy)
    job = run_job(path, three)
    assert len(calls) == 1
    names, pace = calls[0]
    pair = next(c for c in job.candidates if c.arms == names and c.seam_turn_deg == 0 and c.seam_offsets is None)
    assert pair.pace is None                        # the plan kept is the one by volume ...
    monkeypatch.setattr(ambots.job, "_cooperative", real_cooperative)
    given = run_job(path, three, [three.arm(n) for n in names]).chosen
    assert given.pace is None and given.makespan_s == pytest.approx(pair.makespan_s, rel=1e-9)
    busy = given.busy_s
    mean = sum(busy.values()) / len(busy)
    assert pace == {n: round(b / mean, PACE_DIGITS) for n, b in busy.items()}      # ... its variants the pace
