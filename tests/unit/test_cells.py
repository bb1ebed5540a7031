"""The example cells of three, four and eight arms (config/cells/): each
loads, every arm reaches its share of the bed, and jobs run offline through
partition, concurrent (or sequential) schedule and every arm's firmware on
one clock (``python -m ambots plan``) to the end with no collision.  The
demo model is printed at half size to keep the runs short."""
import pytest

from ambots import data_path
from ambots.commands.plan import plan_job
from ambots.config import load_cell
from ambots.job import DEMO_MODEL

CELLS = ["kinova_ur10", "three_arms", "four_arms", "eight_arms_beam"]
DEMO = data_path(*DEMO_MODEL.split("/"))


def cell_path(name):
    return data_path("config", "cells", name + ".yaml")


@pytest.mark.parametrize("name", CELLS)
def test_every_arm_reaches_all_of_its_share_of_the_bed(name):
    """``python -m ambots cell``'s check: the bed split among the arms like a
    model; every point of an arm's part (at the bed and at the printable
    height), nozzle down, in that arm's reach."""
    from ambots.commands.cell import _shares
    from ambots.model import arm_kinematics
    from ambots.workspace import bed_reachability
    cell = load_cell(cell_path(name))
    assert len({a.id for a in cell.arms}) == len(cell.arms)
    owner, pts = _shares(cell)
    assert (owner >= 0).all()
    for i, arm in enumerate(cell.arms):
        mine = pts[owner == i]
        assert len(mine) > 0.5 * len(pts) / len(cell.arms)
        ok = bed_reachability(cell, arm, arm_kinematics(arm), mine)
        assert ok.all(), "%s misses %d of %d points of its share" % (arm.name, (~ok).sum(), len(ok))


def test_the_cells_have_the_arms_the_issue_asks_for():
    brands = {name: sorted(a.profile.name for a in load_cell(cell_path(name)).arms) for name in CELLS}
    assert brands["three_arms"] == ["kinova_gen3", "panda", "ur10"]
    assert brands["four_arms"] == ["kinova_gen3", "kinova_gen3", "ur10", "ur10"]
    assert len(brands["eight_arms_beam"]) == 8 and set(brands["eight_arms_beam"]) == {"kinova_gen3", "ur10"}
    beam = load_cell(cell_path("eight_arms_beam"))
    ys = [a.base_xyz[1] for a in beam.arms]
    assert sum(y > 0 for y in ys) == 4 and sum(y < 0 for y in ys) == 4


def assert_clean(rep):
    assert rep["finished"], rep["reason"]
    assert rep["collisions"] == {"arm_arm": 0, "arm_bed": 0, "arm_part": 0}, rep["collisions"]
    assert rep["min_clearance_mm"] > 0 and not rep["errors"]
    for name, arm in rep["arms"].items():
        assert arm["state"] == "DONE" and arm["ik_failures"] == 0, name
        assert arm["filament_mm"] > 0, "%s printed nothing" % name
    # walls and 20 % infill: between a third and all of the model's volume
    assert 0.3 * rep["model_volume_mm3"] < rep["deposit_volume_mm3"] < rep["model_volume_mm3"]


@pytest.fixture(scope="module")
def three_arms():
    cell = load_cell(cell_path("three_arms"))
    return plan_job(DEMO, cell, list(cell.arms), scale=0.5)       # all three: not the planner's choice


def test_three_arms_with_the_panda_print_concurrently_to_the_end_without_collision(three_arms):
    """The first three-arm trial deadlocked in the first layer and had the
    Kinova run into the UR10; now every arm, the Panda included, prints its
    part to the end."""
    rep = three_arms
    assert rep["mode"] == "concurrent" and set(rep["arms"]) == {"kinova", "ur10", "panda"}
    assert_clean(rep)


def test_three_arms_in_sequence_park_out_of_the_printing_arm_s_way():
    """Sequential mode: the waiting arms park clear of the bed (the Panda's
    home pose hangs over it, where the first trial left it to be hit)."""
    rep = _three_in_sequence()
    assert rep["mode"] == "sequential"
    assert rep["collisions"]["arm_arm"] == 0 and rep["collisions"]["arm_bed"] == 0
    assert_clean(dict(rep, collisions=dict(rep["collisions"], arm_part=0)))


def test_three_arms_in_sequence_never_touch_the_part():
    """Each arm prints beside the slabs of the arms before it: in rounds
    (the block's 5 mm in two), so that no head comes down on another arm's
    finished part (it did with each part whole, the head at the seam; the
    part is checked as the box around every bead laid so far)."""
    rep = _three_in_sequence()
    assert rep["collisions"]["arm_part"] == 0 and rep["min_part_clearance_mm"] > 0


_SEQ = {}


def _three_in_sequence():
    if not _SEQ:
        _SEQ["rep"] = plan_job(DEMO, load_cell(cell_path("three_arms")), mode="sequential", scale=0.5)
    return _SEQ["rep"]


def test_four_arms_in_the_corners_print_concurrently_to_the_end_without_collision():
    cell = load_cell(cell_path("four_arms"))
    rep = plan_job(DEMO, cell, list(cell.arms), scale=0.5)        # all four: not the planner's choice
    assert_clean(rep)
    assert len(rep["arms"]) == 4
    # concurrently: the job takes less than the arms' printing one after the other
    assert rep["makespan_s"] < sum(a["print_time_s"] for a in rep["arms"].values())
