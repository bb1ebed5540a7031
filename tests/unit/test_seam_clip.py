"""An arm's part of a straight seam is the whole model's toolpaths clipped to
its prism (ambots.seam_clip): checked against the whole model's G-code
(every line printed once, by the arm whose prism holds it), against the
partition's planes, and against slicing each part on its own (which puts
walls on the seam faces)."""
import math

import numpy as np
import pytest
import trimesh

from ambots.config import default_cell_path, load_cell
from ambots.coordinate import read_sliced
from ambots.job import prepare_model, run_job, slice_parts, split
from ambots.seam_clip import clip_paths
from ambots.slicer import EXTERNAL_PERIMETER, PERIMETER, SOLID_INFILL, Path, SliceSettings, WholeModel
from test_slicer import Toolpath  # tests/unit/test_slicer.py


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def walls_along(text, n, off):
    """Perimeter moves (``;TYPE:`` a perimeter) over 1 mm long along the
    plane (n, off), within 0.6 mm of it."""
    tp = Toolpath(text)
    wall = np.isin(tp.feature, [EXTERNAL_PERIMETER, PERIMETER]) & tp.extruding
    d0, d1 = tp.start @ np.asarray(n) - off, tp.end @ np.asarray(n) - off
    return int(np.sum(wall & (np.abs(d0) < 0.6) & (np.abs(d1) < 0.6) & (tp.length > 1.0)))


def extrusions(text):
    """(start (S, 3), end (S, 3), E (S,)) of the segments that lay filament."""
    segs = [s for v in read_sliced(text, "x").layers.values() for s in v if s.extrude and s.start != s.end]
    return (np.array([s.start for s in segs]), np.array([s.end for s in segs]), np.array([s.e for s in segs]))


@pytest.fixture(scope="module", params=["block", "ring"])
def job(request, cell, tmp_path_factory):
    path = tmp_path_factory.mktemp("m") / (request.param + ".stl")
    if request.param == "block":
        trimesh.creation.box((160.0, 40.0, 3.0)).export(str(path))
    else:
        trimesh.creation.annulus(30.0, 45.0, 3.0, sections=96).export(str(path))
    mesh = prepare_model(str(path), cell)
    parts = split(mesh, cell, list(cell.arms))
    whole = WholeModel(mesh, SliceSettings())
    return parts, whole, slice_parts(parts, "builtin", None, whole), slice_parts(parts, "builtin", None, whole,
                                                                               clip=False), mesh


def seam_chord_mm(mesh, n, off):
    """How far the seam plane (n, off) runs through the model, mm: the area
    of the model's section by the plane over the model's height."""
    section = mesh.section(plane_origin=np.asarray(n, float) * off, plane_normal=np.asarray(n, float))
    planar, _ = section.to_2D()
    return planar.area / float(mesh.extents[2])


def test_the_parts_print_the_whole_models_lines_once(job):
    """Every extrusion of the whole model's G-code is printed by exactly one
    arm: the parts' lengths and filament add up to the whole's plus the
    zig-zag links along the seam (the two arms' links alternate, so at most
    the plane's chord through the model once a layer), and every part's
    extrusions lie in its prism."""
    parts, whole, clipped, _, mesh = job
    S, E, e = extrusions(whole.text())
    length = np.linalg.norm(E - S, axis=1).sum()
    layers = len(read_sliced(whole.text(), "x").layers)
    (n, off), = parts[0].planes
    links_max = layers * seam_chord_mm(mesh, n, off)
    got_len = got_e = 0.0
    for p in parts:
        s, t, pe = extrusions(clipped[p.arm.name])
        got_len += np.linalg.norm(t - s, axis=1).sum()
        got_e += pe.sum()
        for n, off in p.planes:              # in the prism, to the G-code's 0.001 mm
            assert (np.concatenate([s, t]) @ np.asarray(n) - off).min() > -0.001
    assert length < got_len <= length + links_max
    assert got_e == pytest.approx(e.sum() * got_len / length, rel=1e-4)


def test_no_walls_on_the_seam_faces(job):
    """Sliced each on its own, both parts have perimeters along the seam
    (perimeter moves over 1 mm long along it, within 0.6 mm of it: the
    outer one on every layer); clipped, none."""
    parts, _, clipped, alone, _ = job

    for p in parts:
        for n, off in p.planes:
            assert walls_along(alone[p.arm.name], n, off) >= 10       # one a layer at least
            assert walls_along(clipped[p.arm.name], n, off) == 0


def test_a_loop_cut_by_a_plane_gives_each_side_its_arc():
    """A 20 mm square loop cut at x = 3: the side x >= 3 gets one open piece
    from (3, -10) round to (3, 10), the side x < 3 the rest; the two add up
    to the loop, and a loop wholly inside stays a loop."""
    sq = Path("perimeter", np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]), True)
    n = np.array([1.0, 0.0])
    right = clip_paths([sq], [(n, 3.0, 1)])
    left = clip_paths([sq], [(n, 3.0, -1)])
    assert len(right) == len(left) == 1 and not right[0].closed and not left[0].closed
    lengths = [float(np.linalg.norm(np.diff(p.points, axis=0), axis=1).sum()) for p in right + left]
    assert lengths[0] == pytest.approx(7 + 20 + 7) and lengths[1] == pytest.approx(80 - 34)
    ends = {tuple(np.round(right[0].points[i], 9)) for i in (0, -1)}
    assert ends == {(3.0, -10.0), (3.0, 10.0)}
    assert clip_paths([sq], [(n, -20.0, 1)]) == [sq] and clip_paths([sq], [(n, 20.0, 1)]) == []


def test_infill_cut_by_a_plane_is_joined_along_it():
    """A zig-zag of solid infill lines 0.5 mm apart cut at x = 0: each side
    gets one zig-zag again, joined on the plane (links under 0.9 mm), with
    the links alternating between the sides; sparse lines 3 mm apart stay
    apart."""
    ys = np.arange(10) * 0.5
    pts = np.array([[(-10.0, y), (10.0, y)][::1 if k % 2 == 0 else -1] for k, y in enumerate(ys)]).reshape(-1, 2)
    lane = Path(SOLID_INFILL, pts, False)
    n = np.array([1.0, 0.0])
    right = clip_paths([lane], [(n, 0.0, 1)], link_max=0.9)
    left = clip_paths([lane], [(n, 0.0, -1)], link_max=0.9)
    assert len(right) == len(left) == 1
    on = lambda p: [tuple(q) for q in p.points if abs(q[0]) < 1e-12]
    links_r, links_l = on(right[0]), on(left[0])
    assert len(links_r) == len(links_l) == 10                    # every line meets the plane once per side
    assert math.isclose(sum(np.linalg.norm(np.diff(p.points, axis=0), axis=1).sum() for p in right + left),
                        10 * 20 + 9 * 0.5 + 9 * 0.5)             # the outer links plus one per pair at the seam
    wide = Path(SOLID_INFILL, pts * [1.0, 6.0], False)
    assert len(clip_paths([wide], [(n, 0.0, 1)], link_max=0.9)) == 5


def test_the_job_clips_the_parts_of_two_and_of_four_arms(tmp_path):
    """The job's plans take the clipped toolpaths (the whole model's name in
    each part's G-code, no walls on the seam faces) for two arms and for a
    scheduled timeline of four arms around the centre."""
    from ambots import data_path
    path = tmp_path / "plate.stl"
    trimesh.creation.box((200.0, 200.0, 1.0)).export(str(path))
    four = load_cell(data_path("config", "cells", "four_arms.yaml"))
    for cell, arms in ((four, list(four.arms)), (load_cell(default_cell_path()), None)):
        job = run_job(str(path), cell, arms)
        assert len(job.sliced) == len(cell.arms) and all("\n; model: plate.stl\n" in t for t in job.sliced.values())
        scheduled = all(p.chunk_bands is not None for p in job.programs.values())
        assert scheduled == (cell is four)
        for p in job.parts:
            assert all(walls_along(job.sliced[p.arm.name], n, off) == 0 for n, off in p.planes)


def test_a_point_on_a_plane_within_the_g_codes_rounding_is_on_it():
    """The scheduled timeline measures a point less than 0.001 mm across a
    plane (a clipped line's end, rounded to the G-code's 0.001 mm) as on the
    plane; a point farther across stays across."""
    from types import SimpleNamespace

    from ambots.coordinate.timeline import Seams
    seams = SimpleNamespace(N={"a": np.array([[1.0, 0.0, 0.0]])}, O={"a": np.array([10.0])})
    d = Seams.dist(seams, "a", [[9.9996, 0, 0], [9.99, 0, 0], [10.5, 0, 0], [10.0, 0, 0]])
    assert d[:, 0].tolist() == [0.0, pytest.approx(-0.01), pytest.approx(0.5), 0.0]
