"""Makespan estimates (ambots.estimate) and the planner's choice of plan
(ambots.job.run_job), checked against independent measures: the firmware's
runner executing a program on its own clock, the offline simulation of all
arms on one clock (every move planned, the hub's messages), and hand-worked
schedules."""
import re

import numpy as np
import pytest
import trimesh

from ambots.config import default_cell_path, load_cell
from ambots.estimate import EstimateError, ProgramTimes, estimate_programs, line_durations, makespan, program_time
from ambots.job import TIE_SHARE, run_job
from ambots.protocol import LoadChunk, Start, WaitFor
from ambots.runner import ArmRunner
from ambots.sim import simulate


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def growing_squares(layers=12):
    """A square that grows layer by layer (layers that differ), with a
    retraction and a dwell per layer."""
    lines = ["G21", "G90", "M83"]
    for layer in range(layers):
        z = 0.2 * (layer + 1)
        half = 10.0 + 2.0 * layer
        lines += [";LAYER_CHANGE", ";Z:%.1f" % z, "G0 X%.1f Y%.1f Z%.1f F9000" % (-half, -half, z)]
        for x, y in ((half, -half), (half, half), (-half, half), (-half, -half)):
            lines.append("G1 X%.1f Y%.1f E%.3f F1800" % (x, y, 0.05 * half))
        lines += ["G1 E-0.8 F2100", "G4 P200", "G1 E0.8 F2100"]
    return "\n".join(lines) + "\n"


def runner_time(arm, cell, text):
    r = ArmRunner(arm, cell)
    r.handle(LoadChunk(arm.id, text, chunk_id=1))
    r.handle(Start(arm.id), now=0.0)
    t = 0.0
    while r.state.name not in ("DONE", "ERROR") and t < 1e5:
        t += 5.0
        r.advance(t)
    assert r.state.name == "DONE"
    return r.stats.done_s


def test_a_program_planned_whole_takes_the_runners_time_and_a_sample_stays_close(cell):
    """Every run planned: the time the firmware's runner takes for the same
    program (the move from home is planned the same way; within 1 %).  With
    a sample of a sixth of the moves and the per-move model elsewhere:
    within 3 % of that."""
    arm = cell.arm("ur10")
    text = growing_squares()
    truth = runner_time(arm, cell, text)
    full = line_durations(text, arm, cell, sample_moves=10 ** 9)
    assert full.planned_moves == full.moves
    assert full.total_s == pytest.approx(truth, rel=0.01)
    sampled = line_durations(text, arm, cell, sample_moves=full.moves // 6)
    assert sampled.planned_moves < full.moves // 3
    assert sampled.total_s == pytest.approx(truth, rel=0.03)
    # a move out of reach: no time
    far = text.replace("X-10.0 Y-10.0 Z0.2", "X-5000.0 Y-10.0 Z0.2")
    assert program_time(far, arm, cell) is None
    assert "line 6" in line_durations(far, arm, cell, "far.gcode").error


def mixed_layers(per_layer=300):
    """Eight layers of one run each, four kinds of path in turn: a circle of
    short chords, a zigzag of 2 mm legs, 80 mm infill lines, a square
    spiral of growing legs."""
    lines = ["G21", "G90", "M83"]
    k = np.arange(per_layer + 1)
    for layer in range(8):
        z = 0.2 * (layer + 1)
        if layer % 4 == 0:
            a = np.linspace(0.0, 2.0 * np.pi, per_layer + 1)
            pts = np.c_[40.0 * np.cos(a), 40.0 * np.sin(a)]
        elif layer % 4 == 1:
            pts = np.c_[-60.0 + 0.4 * k, np.where(k % 2, 1.0, -1.0)]
        elif layer % 4 == 2:
            pts = np.c_[np.where(k % 2, 40.0, -40.0), -30.0 + 0.2 * k]
        else:
            legs = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])[k[:-1] % 4] * (0.5 + 0.25 * k[:-1, None])
            pts = 0.6 * np.vstack([[0.0, 0.0], np.cumsum(legs, axis=0)])
        lines += [";LAYER_CHANGE", ";Z:%.1f" % z, "G0 X%.3f Y%.3f Z%.1f F9000" % (pts[0, 0], pts[0, 1], z)]
        lines += ["G1 X%.3f Y%.3f E0.05 F2400" % (x, y) for x, y in pts[1:]]
    return "\n".join(lines) + "\n"


def test_a_sample_of_a_quarter_of_the_moves_times_layers_unlike_each_other_within_one_percent(cell):
    """Each layer is one run and no two neighbours are alike: the sample
    must see every kind of path, not a few whole runs (a sample of the
    first run and whole runs spread over the program was 12.5 % over
    here).  Against every move planned by the firmware's planner."""
    arm = cell.arm("ur10")
    text = mixed_layers()
    full = line_durations(text, arm, cell, sample_moves=10 ** 9)
    sampled = line_durations(text, arm, cell, sample_moves=600)
    assert sampled.planned_moves <= full.moves // 4
    assert sampled.total_s == pytest.approx(full.total_s, rel=0.01)


class _Arm:
    def __init__(self, name, id_):
        self.name, self.id = name, id_


def _times(durations, directives):
    d = np.concatenate([[0.0], np.asarray(durations, float)])
    return ProgramTimes(d, np.zeros(len(d), int), dict(directives))


def test_barriers_and_starts_hold_an_arm_as_worked_out_by_hand():
    a, b, c = _Arm("a", 1), _Arm("b", 2), _Arm("c", 3)
    # a: 10 lines of 1 s.  b: 2 s, then waits (line 2) for a's line 6, then 3 lines of 1 s.
    # c: started by b's last line (line 6), then 4 s.
    ta = _times([1.0] * 10, {})
    tb = _times([2.0, 0.0, 1.0, 1.0, 1.0, 0.0], {2: WaitFor(2, 1, line=6), 6: Start(3)})
    tc = _times([4.0], {})
    out = makespan({"a": ta, "b": tb, "c": tc}, [a, b, c], {"a": True, "b": True, "c": False})
    assert out["arms"]["a"]["finish_s"] == pytest.approx(10.0)
    assert out["arms"]["b"]["finish_s"] == pytest.approx(6.0 + 3.0)        # released at 6
    assert out["arms"]["b"]["idle_s"] == pytest.approx(4.0)                 # 2 .. 6
    assert out["arms"]["c"]["start_s"] == pytest.approx(9.0)
    assert out["arms"]["c"]["finish_s"] == pytest.approx(13.0)
    assert out["makespan_s"] == pytest.approx(13.0)
    # a barrier on a line already done does not hold: b waits for a's line 1 (done at 1 s)
    tb2 = _times([2.0, 0.0, 1.0], {2: WaitFor(2, 1, line=1)})
    assert makespan({"a": ta, "b": tb2}, [a, b])["arms"]["b"]["finish_s"] == pytest.approx(3.0)
    # two arms waiting for each other: refused, naming them
    t1 = _times([1.0, 0.0, 1.0], {2: WaitFor(1, 2, line=3)})
    t2 = _times([1.0, 0.0, 1.0], {2: WaitFor(2, 1, line=3)})
    with pytest.raises(EstimateError, match="a, b"):
        makespan({"a": t1, "b": t2}, [a, b])


def _model(tmp_path, name, mesh):
    path = str(tmp_path / (name + ".stl"))
    mesh.export(path)
    return path


def _box(dims):
    m = trimesh.creation.box(dims)
    m.apply_translation((0.0, 0.0, dims[2] / 2.0))
    return m


@pytest.fixture(scope="module")
def strip_job(cell, tmp_path_factory):
    """Two arms forced on a strip long enough for both to print at once."""
    path = _model(tmp_path_factory.mktemp("est"), "strip", _box((240.0, 20.0, 0.6)))
    return run_job(path, cell, arms=list(cell.arms))


def test_the_estimate_of_two_arms_is_the_simulation_on_one_clock(cell, strip_job):
    """The same programs, every move planned and the arms' barriers passed
    through the hub's messages on one simulated clock: within 3 %."""
    assert strip_job.forced and set(strip_job.programs) == {"kinova", "ur10"}
    est = estimate_programs(strip_job.programs, cell)
    sim = simulate(strip_job.programs, cell)
    assert all(r.state.name == "DONE" for r in sim.runners.values())
    assert est["makespan_s"] == pytest.approx(sim.makespan_s, rel=0.03)
    for name, r in sim.runners.items():
        assert est["arms"][name]["finish_s"] == pytest.approx(r.stats.done_s, rel=0.03)


def test_the_planner_never_chooses_a_slower_plan(cell, tmp_path):
    """A compact part (30 mm: inside the seam zone of the two arms, which
    then take turns) is printed by one arm alone, and the simulation agrees
    that this is faster than the two arms together; each plan is in the
    job's candidates with its makespan."""
    path = _model(tmp_path, "small", _box((30.0, 30.0, 1.0)))
    job = run_job(path, cell)
    assert not job.forced
    plans = {tuple(c.arms): c for c in job.candidates}
    assert set(plans) == {("kinova", "ur10"), ("kinova",), ("ur10",)}
    chosen = job.chosen
    assert len(chosen.arms) == 1 and list(job.programs) == chosen.arms
    both = plans["kinova", "ur10"]
    assert chosen.makespan_s * (1 + TIE_SHARE) <= both.makespan_s or chosen.makespan_s < both.makespan_s
    sim_chosen = simulate(job.programs, cell).makespan_s
    sim_both = simulate(both.programs, cell).makespan_s
    assert sim_chosen < sim_both
    assert chosen.makespan_s == pytest.approx(sim_chosen, rel=0.03)
    # the arm alone parks the other first (A7), which then has no program
    idle = [n for n in ("kinova", "ur10") if n not in job.programs][0]
    assert any(line.startswith(";@A7 R%d " % cell.arm(idle).id) for line in job.programs[chosen.arms[0]].lines)
    summary = job.plan_summary()
    assert summary["arms"] == chosen.arms and summary["speedup"] == pytest.approx(1.0)
    assert summary["best_single_arm_s"] == pytest.approx(chosen.makespan_s, abs=0.1)


def test_an_L_is_printed_with_the_seam_turned_when_that_is_faster(cell, tmp_path):
    """The seam straight across an L (160 x 120 mm, 30 mm legs) runs along
    its upright leg, all of it within the seam zone, so the arms take
    turns there; cooperating pays, so the planner also makes the plan with
    the seam turned +-30 deg and keeps the fastest.  The simulation on one
    clock agrees that the plan chosen (a turned seam) is faster than the
    straight one and finds no contact, as planned and with every move of
    each arm 0.5-2x slower at random."""
    from ambots.job import SEAM_TURNS_DEG, _cooperative, plan_lines
    from ambots.sim import check_motion
    leg_x = _box((160.0, 30.0, 0.6))
    leg_x.apply_translation((0.0, -45.0, 0.0))
    leg_y = _box((30.0, 120.0, 0.6))
    leg_y.apply_translation((-65.0, 0.0, 0.0))
    path = _model(tmp_path, "ell", trimesh.boolean.union([leg_x, leg_y], engine="manifold"))
    job = run_job(path, cell)
    both = {c.seam_turn_deg: c for c in job.candidates if len(c.arms) == 2 and c.seam_steps_mm is None}
    assert set(both) == {0.0, *SEAM_TURNS_DEG}
    chosen = job.chosen
    assert chosen.seam_turn_deg != 0.0 and len(chosen.arms) == 2
    assert chosen.makespan_s == min(c.makespan_s for c in job.candidates)
    (n, _), = job.parts[0].planes                      # the Kinova's side, turned from -x
    a = np.radians(chosen.seam_turn_deg)
    assert n == pytest.approx([-np.cos(a), -np.sin(a), 0.0], abs=1e-9)
    zone = lambda c: {float(re.search(r"; seam zone ([0-9.]+) mm", p.text).group(1))      # noqa: E731
                      for p in c.programs.values()}
    assert min(zone(chosen)) >= max(zone(both[0.0]))                                 # the floor
    # the chosen plan's parts (cut again here: it was made in a worker) are the ones its programs print
    from ambots.gcode import Segment
    for part in job.parts:
        (n, off), = part.planes
        ends = np.array([s.end for s in job.events()[part.arm.name] if type(s) is Segment and s.extrude])
        assert (ends @ n - off).min() > -0.5 * 0.45, part.arm.name          # within half a bead of its side
    arms = [cell.arm(n) for n in chosen.arms]
    wider = _cooperative(job, cell, arms, "straight", None, {}, None, "builtin", None, "concurrent", [],
                         chosen.seam_turn_deg, 80.0)[3]                  # a floor over the zone: it holds
    assert zone(wider) == {80.0} and wider.makespan_s > chosen.makespan_s
    assert job.plan_summary()["seam_turn_deg"] == chosen.seam_turn_deg
    assert "seam turned %+g deg" % chosen.seam_turn_deg in plan_lines(job.plan_summary())[0]
    turned = simulate(job.programs, cell)
    straight = simulate(both[0.0].programs, cell)
    assert turned.finished and turned.makespan_s < straight.makespan_s
    assert chosen.makespan_s == pytest.approx(turned.makespan_s, rel=0.03)
    for res in (turned, simulate(job.programs, cell, slow={n: (0.5, 2.0) for n in job.programs}, seed=1)):
        motion = check_motion(res, cell)
        assert res.finished and sum(motion["collisions"].values()) == 0, motion


def test_a_long_part_is_printed_by_both_arms_and_a_flag_forces_the_arms(cell, tmp_path):
    """The demo's shape (240 mm across the seam): both arms, faster than
    the best arm alone by the simulation too; ``arms`` given: that set,
    nothing else considered."""
    path = _model(tmp_path, "long", _box((240.0, 40.0, 0.6)))
    job = run_job(path, cell)
    assert job.chosen.arms == ["kinova", "ur10"] and set(job.programs) == {"kinova", "ur10"}
    alone = min((c for c in job.candidates if len(c.arms) == 1), key=lambda c: c.makespan_s)
    assert simulate(job.programs, cell).makespan_s < simulate(alone.programs, cell).makespan_s
    forced = run_job(path, cell, arms=[cell.arm("ur10")])
    assert forced.forced and [c.arms for c in forced.candidates] == [["ur10"]]
    assert list(forced.programs) == ["ur10"]


def test_moves_that_all_look_alike_get_one_model_whatever_the_last_bits():
    """The per-move fit of a kind whose sampled moves share one row of
    features (a program's lifts: same length, same feed) fits every subset
    of columns equally well; it must keep the first (the feed time), not
    whichever the last bits of the planned times favour: those differ from
    one call to the next (numpy's vector loops depend on memory alignment),
    and the fit applied to the moves outside the sample gave one program
    1,102.4 s or 1,100.9 s."""
    from ambots.estimate import _design, _nonneg_fit
    f, L, corners = np.full(12, 0.0012), np.full(12, 10.0), np.full(12, 2.0)
    X = _design(f, L, corners)
    y = np.full(12, 0.0332)
    fits = set()
    for k in range(40):                     # y moved by a few ulps, one way or the other
        yk = y + np.spacing(y) * ((np.arange(12) * 7 + k) % 5 - 2)
        c = _nonneg_fit(X, yk, np.full(12, 1.0 / 12))
        assert X @ c == pytest.approx(yk, rel=1e-9)
        fits.add(tuple(np.flatnonzero(c)))
    assert fits == {(0,)}
    # a column that really fits better still wins
    L = np.linspace(1.0, 20.0, 12)
    c = _nonneg_fit(_design(L / 50.0, L, np.full(12, 2.0)), 0.01 + 0.002 * np.sqrt(L))
    assert c[0] == pytest.approx(0.0, abs=1e-12) and c[1] == pytest.approx(0.01) and c[2] == pytest.approx(0.002)
