"""The look-ahead order of a scheduled timeline (ambots.coordinate.lookahead):
the list schedule of a layer against schedules worked out by hand, the
search against the layer's bound, and the timeline made with that order
alone kept safe whatever the timing (four arms in the corners, one chunk
band per seam)."""
import random

import numpy as np
import pytest
import trimesh

from ambots.config import load_cell
from ambots.coordinate import home_positions_mm, park_positions_mm, read_sliced, seam_planes, seam_zones_for
from ambots.coordinate.lookahead import _Layer, _search, layer_orders
from ambots.coordinate.parking import JointMoves
from ambots.coordinate.timeline import SCHEDULES, Seams, _chunks, timeline_programs
from ambots.coordinate.zones import adjacent_arms
from test_coordinate import assert_zones_kept

# two arms, each a chunk at the seam (10 s) and one beyond the zone (30 s):
# the two seam chunks conflict; 0 = arm A's seam chunk, 1 its far one,
# 2 arm B's seam chunk, 3 its far one
_ARM = [0, 0, 1, 1]
_DUR = [10.0, 30.0, 10.0, 30.0]


def _conflict(*pairs, k=4):
    m = np.zeros((k, k), dtype=bool)
    for i, j in pairs:
        m[i, j] = m[j, i] = True
    return m


def test_the_list_schedule_of_a_layer_is_the_one_worked_out_by_hand():
    """Seam chunks first on both arms: A prints its seam chunk (0-10 s), B
    cannot and starts its far one (0-30 s), then its seam chunk (30-40 s):
    40 s, the slowest arm's work.  Far chunks first: both 0-30 s, then the
    seam chunks one after the other: 50 s."""
    layer = _Layer(_ARM, _DUR, _conflict((0, 2)), _conflict(), _conflict())
    assert layer.makespan({0: [0, 1], 1: [2, 3]}) == pytest.approx(40.0)
    assert layer.makespan({0: [1, 0], 1: [3, 2]}) == pytest.approx(50.0)
    assert layer.bound() == pytest.approx(40.0)


def test_an_arm_standing_at_its_last_chunk_blocks_its_neighbour():
    """B has only its seam chunk (10 s) and stands where it ends, which A's
    seam chunk conflicts with.  A's far chunk first (0-30 s): B prints its
    seam chunk at once (0-10 s) and then stands in A's way for ever (inf:
    the schedule would send it to its park position).  A's seam chunk
    first (0-10 s): B waits, prints at 10-20 s while A prints its far chunk
    (10-40 s): 40 s."""
    arm, dur = [0, 0, 1], [10.0, 30.0, 10.0]
    fe = np.zeros((3, 3), dtype=bool)
    fe[0, 2] = True                      # A's seam chunk and the end of B's
    layer = _Layer(arm, dur, _conflict((0, 2), k=3), fe, _conflict(k=3))
    assert layer.makespan({0: [1, 0], 1: [2]}) == float("inf")
    assert layer.makespan({0: [0, 1], 1: [2]}) == pytest.approx(40.0)


def test_the_search_finds_the_layers_bound_from_the_worst_order():
    """From far chunks first (50 s) the search reaches 40 s, the slowest
    arm's own work."""
    layer = _Layer(_ARM, _DUR, _conflict((0, 2)), _conflict(), _conflict())
    orders, value = _search(layer, {0: [1, 0], 1: [3, 2]}, 200, random.Random(3))
    assert value == pytest.approx(40.0) and layer.makespan(orders) == pytest.approx(40.0)


@pytest.fixture(scope="module")
def corners(tmp_path_factory):
    """Four arms in the corners of the bed on a 140 x 120 x 0.4 mm box:
    what :func:`timeline_programs` takes."""
    from ambots.job import prepare_model, slice_parts, split
    cell = load_cell("config/cells/four_arms.yaml")
    path = tmp_path_factory.mktemp("models") / "box.stl"
    box = trimesh.creation.box((140.0, 120.0, 0.4))
    box.apply_translation((0.0, 0.0, 0.2))
    box.export(str(path))
    parts = split(prepare_model(str(path), cell), cell, list(cell.arms))
    sliced = slice_parts(parts)
    parts = [p for p in parts if p.arm.name in sliced]
    arms = [p.arm for p in parts]
    read = {a.name: read_sliced(sliced[a.name], a.name) for a in arms}
    planes, zones = seam_planes(parts), seam_zones_for(cell, arms, parts)
    n_layers = max(max(layers) + 1 for layers in (r.layers for r in read.values()))
    return cell, arms, read, planes, zones, adjacent_arms(arms, read, planes, zones), n_layers


def test_layer_orders_rank_every_chunk_and_do_not_change_from_run_to_run(corners):
    """Every chunk of every arm and layer gets a rank (0..chunks-1); the
    layers' list schedules are no shorter than their bounds; the same
    chunks give the same orders (the search is seeded)."""
    cell, arms, read, planes, zones, adjacent, n_layers = corners
    seams = Seams(arms, read, planes, zones, adjacent)
    chunks = _chunks(seams, read, n_layers, 1)
    order, (total, bound) = layer_orders(seams, chunks, n_layers)
    for (n, layer), cs in chunks.items():
        if cs:
            assert sorted(order[n, layer].values()) == list(range(len(cs)))
    assert total >= bound - 1e-6 > 0
    assert layer_orders(seams, chunks, n_layers)[0] == order


@pytest.mark.parametrize("seed", range(3))
def test_the_look_ahead_timeline_keeps_every_pair_a_zone_apart_whatever_the_timing(corners, seed):
    """The timeline made with the look-ahead schedule alone (one chunk band
    per seam, the chunks ending clear of the seams), executed with random
    durations and the firmware's reporting: no deadlock, and every two
    adjacent arms keep their nozzles the zone apart across their plane;
    more than one arm prints at once."""
    cell, arms, read, planes, zones, adjacent, n_layers = corners
    programs = timeline_programs(arms, read, park_positions_mm(cell, arms), home_positions_mm(cell, arms), n_layers,
                                 planes, zones, adjacent, bands=1, kinds=("lookahead",), moves=JointMoves(cell, arms))
    assert all("scheduled" in p.lines[2] for p in programs.values())
    assert_zones_kept(programs, cell, arms, planes, zones, adjacent, seed)


def test_the_timeline_keeps_the_shorter_of_its_chunks_linked_and_as_cut(corners):
    """The chunks' infill linked along their edges (fewer starts from rest)
    and as cut (each line a run the schedule can take in its own order):
    the timeline schedules both (the chunks as cut in the look-ahead order
    only), keeps the shorter by its own estimate, and says which in the
    programs' header; each kind alone is the timeline of that kind."""
    from ambots.coordinate import timeline
    cell, arms, read, planes, zones, adjacent, n_layers = corners
    args = (arms, read, park_positions_mm(cell, arms), home_positions_mm(cell, arms), n_layers, planes, zones,
            adjacent)
    span, header = {}, {}
    for links in ((True,), (False,), None):
        programs = timeline_programs(*args, bands=1, moves=JointMoves(cell, arms), links=links)
        span[links] = max(a[-1].C for a in timeline._last_schedule.values() if a)
        header[links] = {p.lines[2].rsplit(", ", 1)[1] for p in programs.values()}
    assert header[(True,)] == {"infill linked along chunk edges"}
    assert header[(False,)] == {"infill not linked along chunk edges"}
    assert span[(True,)] != span[(False,)]               # the two kinds are different schedules
    assert span[None] == min(span[(True,)], span[(False,)])
    assert header[None] == header[(True,) if span[(True,)] <= span[(False,)] else (False,)]
    seams = Seams(arms, read, planes, zones, adjacent)
    linked, cut = (_chunks(seams, read, n_layers, 1, links) for links in (True, False))
    assert sum(len(ps) for cs in linked.values() for ps, _, _ in cs) > sum(len(ps) for cs in cut.values()
                                                                        for ps, _, _ in cs)
    with pytest.raises(ValueError, match="links"):
        timeline_programs(*args, links=("both",))
    with pytest.raises(ValueError, match="as cut"):                 # only the look-ahead order
        timeline_programs(*args, links=(False,), kinds=("greedy",))


def test_unknown_schedules_are_refused(corners):
    cell, arms, read, planes, zones, adjacent, n_layers = corners
    with pytest.raises(ValueError, match="lookahead"):
        timeline_programs(arms, read, park_positions_mm(cell, arms), home_positions_mm(cell, arms), n_layers,
                          planes, zones, adjacent, kinds=("fastest",))
    assert SCHEDULES == ("priority", "greedy", "lookahead")
