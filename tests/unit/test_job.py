"""The slice pipeline end to end: model file -> per-arm programs on disk."""
import json
import re
import subprocess
import sys

import manifold3d as m3
import pytest
import trimesh

from ambots import data_path
from ambots.config import default_cell_path, load_cell
from ambots.errors import MeshError
from ambots.gcode import Segment, read_gcode, summarize_file
from ambots.job import VARIANT_SHARE, run_job, write_job


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def cube_stl(tmp_path_factory):
    path = tmp_path_factory.mktemp("models") / "cube 40 'mm'.stl"
    trimesh.creation.box([40, 40, 10]).export(str(path))
    return str(path)


def slice_cli(*args):
    return subprocess.run([sys.executable, "-m", "ambots", "slice", *args], capture_output=True, text=True)


@pytest.mark.parametrize("slicer, mode", [("builtin", "concurrent"), ("prusa", "sequential")])
def test_slice_writes_one_program_and_part_per_arm(tmp_path, cube_stl, slicer, mode):
    out = tmp_path / "out"
    r = slice_cli(cube_stl, "--slicer", slicer, "--mode", mode, "--out", str(out), "--arms", "kinova,ur10")
    assert r.returncode == 0, r.stderr
    assert "kinova   R0" in r.stdout and "ur10     R1" in r.stdout
    summary = json.loads((out / "job.json").read_text())
    assert summary["mode"] == mode and summary["slicer"] == slicer
    vols = []
    for arm in ("kinova", "ur10"):
        info = summarize_file(str(out / (arm + ".gcode")))      # reads without error
        assert info["layers"] == 50 and info["extruded_filament_mm"] > 0
        part = trimesh.load(str(out / (arm + ".stl")))
        vols.append(part.volume)
        # every extrusion stays on the arm's side of the seam (+- one bead)
        xs = [x for ev in read_gcode(str(out / (arm + ".gcode")))
              if type(ev) is Segment and ev.extrude and ev.start != ev.end for x in (ev.start[0], ev.end[0])]
        if arm == "kinova":
            assert max(xs) <= 0.45 and min(xs) >= -20.45
        else:
            assert min(xs) >= -0.45 and max(xs) <= 20.45
    assert sum(vols) == pytest.approx(40 * 40 * 10, rel=1e-3)


def test_the_per_arm_times_are_the_plans_timing_law_not_the_feeds(tmp_path, cube_stl, cell):
    """The slice summary's per-arm ``busy s`` and ``done s`` are the one
    timing law's, on the plan's clock: the last arm done is the plan's
    makespan, each arm's busy time is its program timed alone (read back
    from the file written), and no arm moves faster than its programmed
    feedrates allow (``print_time_s``: length / feedrate, no acceleration,
    a lower bound of any motion that keeps to the feeds)."""
    from ambots.estimate import program_time
    out = tmp_path / "out"
    r = slice_cli(cube_stl, "--out", str(out), "--arms", "kinova,ur10")
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "job.json").read_text())
    arms = summary["arms"]
    assert max(a["done_s"] for a in arms.values()) == pytest.approx(summary["plan"]["makespan_estimate_s"], abs=0.1)
    header = next(l for l in r.stdout.splitlines() if l.split()[:2] == ["arm", "id"])
    assert header.split()[-4:] == ["busy", "s", "done", "s"] and "time s" not in r.stdout
    for name, a in arms.items():
        text = (out / (name + ".gcode")).read_text()
        assert a["busy_s"] == pytest.approx(program_time(text, cell.arm(name), cell), abs=0.1)
        assert a["print_time_s"] < a["busy_s"] <= a["done_s"]
        assert a["done_s"] == pytest.approx(a["busy_s"] + a["idle_s"], abs=0.2)
        row = next(l for l in r.stdout.splitlines() if l.split()[:1] == [name])
        assert row.split()[-2:] == ["{:,.0f}".format(a["busy_s"]), "{:,.0f}".format(a["done_s"])]


def test_one_arm_alone_prints_everything(tmp_path, cube_stl, cell):
    job = run_job(cube_stl, cell, arms=[cell.arm("ur10")])
    summary = write_job(job, str(tmp_path))
    assert list(summary["arms"]) == ["ur10"]
    assert summary["arms"]["ur10"]["part_volume_mm3"] == pytest.approx(16000, rel=1e-6)
    assert not any(l.startswith(";@A9") for l in job.programs["ur10"].lines)


def test_a_job_parses_each_g_code_once(tmp_path, cube_stl, cell, monkeypatch):
    """The planner's three plans (both arms; each arm alone on the same
    G-code of the whole model): every sliced G-code is parsed once, and no
    program is parsed at all: the estimate and job.json use the events the
    emitter kept, which are the parser's.  The built-in slicer's G-code is
    not parsed either: it comes with its writer's reading, the parser's.
    In one process (``AMBOTS_JOBS=1``): a worker's parses are not counted
    here.  The slower arm alone keeps no programs (a worker sends back only
    the fastest's, the only one that can be chosen)."""
    import ambots.gcode
    from ambots.coordinate import read_sliced
    parsed = []
    real = ambots.gcode.iter_gcode

    def counting(lines, *args, **kw):
        lines = list(lines)
        parsed.append("\n".join(lines))
        return real(lines, *args, **kw)

    monkeypatch.setattr(ambots.gcode, "iter_gcode", counting)
    monkeypatch.setenv("AMBOTS_JOBS", "1")
    for slicer in ("prusa", "builtin"):
        parsed.clear()
        job = run_job(cube_stl, cell, slicer=slicer)
        write_job(job, str(tmp_path / slicer))
        kept = [c for c in job.candidates if c.programs]
        alone = sorted((c for c in job.candidates if c.how == "alone"), key=lambda c: c.makespan_s)
        assert len(job.candidates) == 3 and job.chosen in kept and alone[0] in kept and alone[1] not in kept
        programs = [p.text.rstrip("\n") for c in kept for p in c.programs.values()]
        assert len(programs) == 3 and not any(text in parsed for text in programs)
        if slicer == "prusa":
            assert len(parsed) == len(set(parsed)) == 3          # the pair's parts, the whole model
        else:
            assert parsed == []
            for text in job.sliced.values():
                assert text.layers is not None
                assert read_sliced(text, "x") == read_sliced(str(text), "x")
        for c in kept:
            for name, program in c.programs.items():
                assert program.parse() == list(real(program.text.splitlines(), name + ".gcode"))


def test_a_model_larger_than_the_bed_is_refused_saying_by_how_much(tmp_path, cell):
    big = tmp_path / "big.stl"
    trimesh.creation.box([350, 100, 10]).export(str(big))
    with pytest.raises(MeshError, match=r"350\.0 mm wide in x, bed is 300\.0 mm: 50\.0 mm too large"):
        run_job(str(big), cell)
    r = slice_cli(str(big), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "50.0 mm too large" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("dims, cells, scale", [
    ((1000, 30, 20), ["eight_arms_beam"], 0.3),                  # a beam: the beam cell's bed
    ((100, 100, 400), [], 0.375),                               # too high for every shipped cell
    ((500, 500, 2), ["four_arms"], 0.6),                        # a wide plate: the four-arm cell
])
def test_a_model_too_large_names_the_cells_that_take_it_and_the_scale_that_fits(tmp_path, cell, dims, cells, scale):
    from ambots.config import load_cell as load
    from ambots.job import DoesNotFit, prepare_model, shipped_cells
    big = tmp_path / "big.stl"
    trimesh.creation.box(dims).export(str(big))
    with pytest.raises(DoesNotFit) as info:
        prepare_model(str(big), cell)
    text = str(info.value)
    named = re.findall(r"cell (\w+) \(--cell (\S+)\)", text)
    assert [n for n, _ in named] == cells, text
    assert info.value.scale_to_fit == scale and text.endswith("; cell kinova_ur10 takes it at --scale %g" % scale)
    # independently: each cell named holds the model (bed and height), the others do not
    for c in shipped_cells():
        size = (c.bed.size[0] * 1e3, c.bed.size[1] * 1e3, c.bed.max_height * 1e3)
        assert (c.name in cells) == all(d <= s for d, s in zip(dims, size)) or c.name == cell.name, c.name
    for name, path in named:
        prepare_model(str(big), load(data_path(path)))         # the --cell given is right
    prepare_model(str(big), cell, scale=scale)                   # and so is the scale


def test_unknown_arm_and_missing_file_are_clear_errors(tmp_path, cube_stl):
    r = slice_cli(cube_stl, "--arms", "panda", "--out", str(tmp_path))
    assert r.returncode == 2 and "unknown arm 'panda'" in r.stderr
    r = slice_cli(str(tmp_path / "nope.stl"), "--out", str(tmp_path))
    assert r.returncode == 2 and "nope.stl" in r.stderr and "Traceback" not in r.stderr


def test_a_scheduled_plan_keeps_its_fastest_chunk_bands(tmp_path):
    """Four arms in the corners are a scheduled timeline: the job builds it
    with each of CHUNK_BAND_CHOICES chunk bands per seam and keeps the
    fastest.  Each alternative, built again here from the job's parts and
    G-code and timed by the one timing law, is no faster than the plan
    kept, and at least two of them differ (the choice matters)."""
    from ambots.coordinate import CHUNK_BAND_CHOICES
    from ambots.estimate import estimate_programs
    from ambots.job import coordinate
    cell = load_cell(data_path("config", "cells", "four_arms.yaml"))
    path = str(tmp_path / "plate.stl")
    box = trimesh.creation.box([150.0, 150.0, 0.6])
    box.apply_translation((0.0, 0.0, 0.3))
    box.export(path)
    job = run_job(path, cell, list(cell.arms))
    kept = job.candidates[0].makespan_s
    bands = {p.chunk_bands for p in job.programs.values()}
    assert len(bands) == 1 and bands <= set(CHUNK_BAND_CHOICES), bands
    times = {}
    for b in CHUNK_BAND_CHOICES:
        programs = coordinate(job.sliced, job.parts, cell, chunk_bands=b)
        assert {p.chunk_bands for p in programs.values()} == {b}
        times[b] = estimate_programs(programs, cell)["makespan_s"]
    assert kept <= min(times.values()) + 1e-6, (kept, times)
    assert times[bands.pop()] == pytest.approx(kept, abs=1e-6)
    assert max(times.values()) > min(times.values()) * 1.001, times


def test_a_job_is_planned_with_fewer_collections_and_the_collector_is_restored(tmp_path, monkeypatch):
    """run_job and write_job raise the collector's first threshold to
    GC_THRESHOLD while they work, and put it back after, also when the job
    fails."""
    import gc
    import trimesh
    from ambots import job as J
    cell = load_cell(default_cell_path())
    path = str(tmp_path / "cube.stl")
    trimesh.creation.box((20.0, 20.0, 2.0)).apply_translation((0, 0, 1.0)).export(path)
    seen = []
    real = J._plan_job
    monkeypatch.setattr(J, "_plan_job", lambda *a, **k: seen.append(gc.get_threshold()) or real(*a, **k))
    before = gc.get_threshold()
    job = J.run_job(path, cell, [cell.arms[0]])
    assert seen and seen[0][0] == max(before[0], J.GC_THRESHOLD) and seen[0][1:] == before[1:]
    assert gc.get_threshold() == before
    J.write_job(job, str(tmp_path / "out"))
    assert gc.get_threshold() == before
    with pytest.raises(Exception):
        J.run_job(str(tmp_path / "missing.stl"), cell)
    assert gc.get_threshold() == before


def test_a_job_planned_again_gives_the_same_programs(cell):
    """The same model and cell give byte-identical programs every time: the
    estimate's planned times differ in their last bits from one call to the
    next (numpy's vector loops depend on memory alignment), and before the
    fit kept the first of equal fits and the rebalancing pace was rounded
    (``PACE_DIGITS``), the demo block's plan was one of three (5,098.1,
    5,098.5 or 5,100.0 s) from one run to the next in one process."""
    runs = []
    for _ in range(3):
        job = run_job(data_path("config", "models", "demo_block.stl"), cell)
        assert job.chosen.arms == ["kinova", "ur10"]        # the plan that is split again
        runs.append((round(job.chosen.makespan_s, 6), {n: p.text for n, p in job.programs.items()}))
    assert runs[1] == runs[0] and runs[2] == runs[0]
    # a seam turned or stepped is kept only when clearly faster (VARIANT_SHARE); one faster by less says so
    chosen = job.chosen
    for c in job.candidates[1:]:
        if len(c.arms) == 2 and c.makespan_s is not None and c.makespan_s < chosen.makespan_s:
            assert c.programs is None and "which is kept" in c.note
            assert c.makespan_s >= chosen.makespan_s * (1.0 - VARIANT_SHARE)
