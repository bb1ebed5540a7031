"""Partition of a model among the arms of a cell."""
import manifold3d as m3
import numpy as np
import pytest
import yaml

from ambots import data_path
from ambots.config import default_cell_path, load_cell
from ambots.errors import MeshError
from ambots.partition import arm_sites_mm, partition


def cube():
    return m3.Manifold.cube([40, 40, 40]).translate([-20, -20, 0])


def cylinder():
    return m3.Manifold.cylinder(50, 25, 25, 64)


def overhang():   # a T: the bar overhangs the stem
    return (m3.Manifold.cube([12, 12, 30]).translate([-6, -6, 0])
            + m3.Manifold.cube([60, 12, 8]).translate([-30, -6, 30]))


def hole_through():
    return (m3.Manifold.cube([50, 50, 30]).translate([-25, -25, 0])
            - m3.Manifold.cylinder(40, 8, 8, 48).translate([0, 0, -5]))


MODELS = {"cube": cube, "cylinder": cylinder, "overhang": overhang, "hole": hole_through}


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def union(parts):
    return m3.Manifold.batch_boolean([p.manifold for p in parts], m3.OpType.Add)


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("seam", ["straight", "interlock"])
def test_parts_union_is_the_model_and_print_times_balance(cell, name, seam):
    model = MODELS[name]()
    parts = partition(model, cell, seam=seam)       # also checks every part is in its arm's reach
    assert [p.arm.name for p in parts] == ["kinova", "ur10"]
    assert abs(union(parts).volume() - model.volume()) <= 1e-3 * model.volume()
    # nothing outside the model
    assert abs((union(parts) - model).volume()) <= 1e-6 * model.volume()
    times = [p.est_time_s for p in parts]
    assert max(times) / min(times) <= 1.10
    total = sum(p.volume for p in parts)
    assert total == pytest.approx(model.volume(), rel=1e-6)     # nothing printed twice


@pytest.mark.parametrize("deg", [30.0, -30.0])
def test_a_turned_seam_is_the_straight_one_turned_and_still_tiles_the_model_in_balance(cell, deg):
    """``turn``: the seam plane's normal is the straight seam's turned by
    the angle (rotation matrix by hand), the parts still tile the model
    with nothing printed twice, and their estimated times balance."""
    model = (m3.Manifold.cube([160, 30, 4]).translate([-80, -60, 0])
             + m3.Manifold.cube([30, 120, 4]).translate([-80, -60, 0]))          # an L
    straight = partition(model, cell)
    parts = partition(model, cell, turn=np.radians(deg))
    (n0, _), = straight[0].planes
    (n1, _), = parts[0].planes
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    assert n1 == pytest.approx([c * n0[0] - s * n0[1], s * n0[0] + c * n0[1], 0.0], abs=1e-9)
    assert parts[1].planes[0][0] == pytest.approx(-n1, abs=1e-9)
    assert sum(p.volume for p in parts) == pytest.approx(model.volume(), rel=1e-6)
    assert abs((union(parts) - model).volume()) <= 1e-6 * model.volume()
    assert max(p.est_time_s for p in parts) / min(p.est_time_s for p in parts) <= 1.01
    # each arm still keeps the side facing it: its part's points lie on its side of the plane
    for part in parts:
        (n, off), = part.planes
        lo, hi = np.array(part.manifold.bounding_box()[:3]), np.array(part.manifold.bounding_box()[3:])
        corners = np.array([[x, y, 0.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])
        assert (corners @ n - off).max() > 0.0


def test_each_arm_gets_the_side_facing_it(cell):
    kinova, ur10 = partition(cube(), cell)
    # Kinova stands at -x of the bed, the UR10 at +x
    assert kinova.manifold.bounding_box()[3] <= 1e-9
    assert ur10.manifold.bounding_box()[0] >= -1e-9


def test_overlap_seam_is_the_interlock_reaching_past_the_plane_by_turns(cell):
    """``overlap`` is the interlock: the Kinova's part reaches d = w/2 + (w -
    h (1 - pi/4)) past the plane x = 0 on even layers and stops d before it
    on odd ones (test_interlock checks it layer by layer)."""
    kinova, ur10 = partition(cube(), cell, seam="overlap")
    d = 0.45 / 2 + 0.45 - 0.2 * (1 - np.pi / 4)
    assert (kinova.manifold ^ ur10.manifold).volume() <= 1e-6
    assert kinova.manifold.bounding_box()[3] == pytest.approx(d, abs=1e-6)
    assert ur10.manifold.bounding_box()[0] == pytest.approx(-d, abs=1e-6)
    assert kinova.manifold.slice(0.1).bounds()[2] == pytest.approx(d, abs=1e-6)
    assert kinova.manifold.slice(0.3).bounds()[2] == pytest.approx(-d, abs=1e-6)


def test_one_arm_gets_everything(cell):
    (part,) = partition(cube(), cell, arms=[cell.arm("ur10")])
    assert part.volume == pytest.approx(cube().volume())


def test_a_model_out_of_reach_is_refused_by_how_much(cell):
    big = m3.Manifold.cube([280, 380, 20]).translate([-140, -190, 0]).translate([0, 0, 600])
    with pytest.raises(MeshError, match=r"out of its reach; worst at .* missed by \d+\.\d mm"):
        partition(big, cell)


def test_four_arms_in_the_corners_get_four_balanced_quarters(tmp_path):
    with open(default_cell_path()) as f:
        data = yaml.safe_load(f)
    prof = {"kinova": data_path("config/arms/kinova_gen3.yaml"), "ur10": data_path("config/arms/ur10.yaml")}
    data["arms"] = [{"name": "a%d" % i, "id": i + 1, "profile": prof["kinova" if i % 2 else "ur10"],
                     "base": {"xyz": [0.48 + x, y, 0.0], "rpy": [0, 0, 0]}}
                    for i, (x, y) in enumerate([(-0.6, -0.6), (0.6, -0.6), (0.6, 0.6), (-0.6, 0.6)])]
    path = tmp_path / "four.yaml"
    path.write_text(yaml.safe_dump(data))
    cell4 = load_cell(str(path))
    model = cylinder()
    parts = partition(model, cell4, check_reach=False)
    assert union(parts).volume() == pytest.approx(model.volume(), rel=1e-3)
    times = [p.est_time_s for p in parts]
    assert max(times) / min(times) <= 1.10
    sites = arm_sites_mm(cell4, cell4.arms)
    for p, s in zip(parts, sites):     # each quarter lies towards its arm
        c = np.mean(np.asarray(p.manifold.to_mesh().vert_properties)[:, :2], axis=0)
        assert np.dot(c, s) > 0


def _reach_message(cell, part, **kw):
    from ambots.partition import _check_reach
    try:
        _check_reach(cell, part, **kw)
    except MeshError as exc:
        return str(exc)
    return "ok"


def _solved_points(monkeypatch, kin):
    """A list that grows by the number of points each ``kin.ik_batch`` call solves."""
    solved, ik = [], kin.ik_batch
    monkeypatch.setattr(kin, "ik_batch", lambda P, *a, **k: (solved.append(len(P)), ik(P, *a, **k))[1])
    return solved


def test_the_reach_check_refuses_a_part_just_past_the_reach_as_solving_every_vertex_does(cell, monkeypatch):
    """A fine ball slid away from the UR10 until the check of every vertex
    (the oracle) refuses it, to within 0.05 mm: the grid check (far fewer
    points solved) accepts it where the oracle does and refuses it, with the
    same message, just past."""
    from ambots.kinematics import shared_arm_kinematics
    from ambots.partition import Part
    arm = cell.arm("ur10")
    ball = m3.Manifold.sphere(8, 128)
    site = arm_sites_mm(cell, [arm])[0]
    away = -site / np.linalg.norm(site)                       # from the base across the bed, 60 mm up
    at = lambda d: Part(arm, ball.translate([*(away * d), 60.0]))
    oracle = lambda d: _reach_message(cell, at(d), exhaustive=True)
    near, far = 0.0, 100.0
    assert oracle(near) == "ok"
    while oracle(far) == "ok":
        near, far = far, far * 2
    while far - near > 0.05:
        mid = (near + far) / 2
        near, far = (mid, far) if oracle(mid) == "ok" else (near, mid)
    solved = _solved_points(monkeypatch, shared_arm_kinematics(arm))
    assert _reach_message(cell, at(near)) == "ok"
    assert 0 < sum(solved) < ball.num_vert() / 4             # the corners, not the vertices
    past = _reach_message(cell, at(far))
    assert past.startswith("the part for arm 'ur10' has ") and "out of its reach" in past
    assert past == oracle(far)


@pytest.mark.parametrize("model, arms", [
    ("ball", None), ("ball", ["kinova"]), ("high_ball", None), ("high_ball", ["kinova"]), ("hole", ["ur10"])])
def test_the_reach_check_agrees_with_solving_every_vertex(cell, model, arms, monkeypatch):
    """The grid check (:func:`ambots.partition._check_reach`, fewer points
    solved than the part has vertices) and the check of every vertex give
    the same verdict and the same message, part by part: in reach, and
    partly out of reach."""
    from ambots.kinematics import shared_arm_kinematics
    models = {"ball": lambda: m3.Manifold.sphere(30, 512).translate([0, 0, 30]),
              # the Kinova reaches about 0.44 m above the bed centre (nozzle down): partly out of reach
              "high_ball": lambda: m3.Manifold.sphere(40, 512).translate([0, 0, 440]),
              "hole": lambda: hole_through().refine(18)}
    parts = partition(models[model](), cell, None if arms is None else [cell.arm(n) for n in arms],
                      check_reach=False)
    for part in parts:
        solved = _solved_points(monkeypatch, shared_arm_kinematics(part.arm))
        fast = _reach_message(cell, part)
        assert 0 < sum(solved) < part.manifold.num_vert()
        monkeypatch.undo()
        assert fast == _reach_message(cell, part, exhaustive=True)
        if model == "high_ball" and arms == ["kinova"]:
            assert "out of its reach" in fast
