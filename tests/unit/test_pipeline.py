"""The whole pipeline on the issue's four models (a cube, a cylinder, a model
with an overhang, a model with a hole through it; tests/unit/shapes.py):
model file -> placed mesh -> one part per arm of the default cell -> built-in
slicer -> coordinated per-arm programs (``ambots.job.run_job``).  Per arm,
its program is checked against its own part, computed independently of the
slicer (trimesh cross-sections + shapely; the slicer uses manifold3d):

- material: the program extrudes (net filament + what is still retracted at
  the end, x the filament's cross-section pi (1.75/2)^2) within +-10 % of
  the volume that the whole model's perimeters and infill predict inside
  the part's prism (:func:`predicted_part_volume`; the job clips the whole
  model's toolpaths to each part, so a seam face has no walls);
- footprint: no extruding move leaves the part's cross-section at its layer
  by more than one bead width;
- the parts' union is the model (volume within 0.1 %) and they do not
  overlap (straight seams).

Helpers (Toolpath, sections, layer_z, settings) are test_slicer's."""
import os

import manifold3d as m3
import numpy as np
import pytest
import shapely

from ambots.config import default_cell_path, load_cell
from ambots.job import run_job
from shapes import MODELS  # tests/unit/shapes.py
from test_slicer import SETTINGS, W, Toolpath, layer_z, sections

NAMES = sorted(MODELS)


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture(scope="module")
def jobs(cell, tmp_path_factory):
    """Each model run through the whole pipeline once (default cell, both
    arms -- these parts are compact, so the planner alone would give each
    to one arm --, builtin slicer, concurrent mode, support off: the checks are
    of the part's own material; support is tests/unit/test_support.py's), from a
    file as a user would give it."""
    folder = tmp_path_factory.mktemp("pipeline")
    out = {}
    for name in NAMES:
        path = os.path.join(str(folder), name + ".stl")
        MODELS[name]().export(path)
        out[name] = run_job(path, cell, list(cell.arms), settings=SETTINGS)   # support off: the part's own material
    return out


def halfplane(n, off, big=1e4):
    """The half-plane n . p >= off of the bed (a large shapely polygon)."""
    n = np.asarray(n, dtype=float)[:2]
    p0, t = n * off, np.array([-n[1], n[0]])
    return shapely.Polygon([p0 - big * t, p0 + big * t, p0 + big * t + big * n, p0 - big * t + big * n])


def predicted_part_volume(mesh, s=SETTINGS, planes=None):
    """Material that perimeters + infill predict for ``mesh`` (mm3); with
    ``planes`` (a part's prism: (n, offset) kept n . p >= offset) for the
    part of the whole model ``mesh`` in that prism: the whole model's
    perimeters and infill there (the job clips the whole model's toolpaths
    to the part, so a seam face gets no perimeters).

    Per layer (trimesh's cross-section at mid-layer, a shapely polygon):

    - perimeter shell: the ring between the outline and its inward offset
      by ``perimeters`` x bead spacing, where the spacing is a bead's
      cross-section / layer height (Slic3r's flow model, ``w - h (1 -
      pi/4)``).  Along a straight outline this is outline length x
      perimeters x spacing; the offset also takes off the corners, which
      matters on narrow parts (the T's 3 mm-wide half stems);
    - interior (the inset): at ``infill_density`` where every layer within
      ``bottom_solid_layers`` below and ``top_solid_layers`` above covers it,
      solid (density 1) elsewhere: the first and last layers and over
      overhangs; the sparse infill's lines are joined along the region's
      boundary (PrusaSlicer's connected infill), in every other gap
      between them: half the boundary's length, one bead spacing wide;

    summed and multiplied by the layer height."""
    h = s.layer_height_mm
    spacing = s.bead_spacing_mm(h)
    polys = sections(mesh, layer_z(s, mesh) - h / 2)
    prism = shapely.intersection_all([halfplane(n, off) for n, off in planes]) if planes else None
    cut = (lambda g: shapely.intersection(g, prism)) if prism is not None else (lambda g: g)
    n, volume = len(polys), 0.0
    for i, poly in enumerate(polys):
        interior = poly.buffer(-s.perimeters * spacing, join_style="mitre")
        shell = cut(poly).area - cut(interior).area
        if i - s.bottom_solid_layers < 0 or i + s.top_solid_layers >= n:
            sparse = links = 0.0
        else:
            window = polys[i - s.bottom_solid_layers:i + s.top_solid_layers + 1]
            region = cut(shapely.intersection(interior, shapely.intersection_all(window)))
            # connected infill: the links between its lines run along every other gap of
            # the region's boundary, half of it, one bead wide
            sparse, links = region.area, 0.5 * region.length * spacing
        volume += h * (shell + sparse * s.infill_density + links + (cut(interior).area - sparse))
    return volume


def arm_parts(job):
    """(part, its program's Toolpath, the part as a trimesh) per arm."""
    return [(p, Toolpath(job.programs[p.arm.name].text), p.to_trimesh()) for p in job.parts]


@pytest.mark.parametrize("name", NAMES)
def test_every_arm_gets_a_part_and_a_program(jobs, cell, name):
    job = jobs[name]
    assert [p.arm.name for p in job.parts] == [a.name for a in cell.arms]
    for part, tp, mesh in arm_parts(job):
        assert not part.empty and tp.extruding.sum() > 100
        assert tp.summary["warnings"] == []
        # every layer of the part is printed
        assert tp.summary["layers"] == len(layer_z(SETTINGS, mesh))


@pytest.mark.parametrize("name", NAMES)
def test_each_part_extrudes_what_perimeters_and_infill_predict(jobs, name):
    for part, tp, mesh in arm_parts(jobs[name]):
        extruded = (tp.summary["extruded_filament_mm"] + tp.summary["retracted_at_end_mm"]) \
            * np.pi * (1.75 / 2) ** 2
        assert extruded == pytest.approx(tp.filament_volume_mm3(), rel=1e-9)   # same filament area
        predicted = predicted_part_volume(jobs[name].mesh, planes=part.planes)
        assert extruded == pytest.approx(predicted, rel=0.10), \
            "%s: %.1f mm3 extruded, %.1f predicted" % (part.arm.name, extruded, predicted)
        # coordination moved the slicer's extrusion into the program, none lost nor added
        sliced = Toolpath(jobs[name].sliced[part.arm.name]).filament_volume_mm3()
        assert extruded == pytest.approx(sliced, rel=1e-3)


@pytest.mark.parametrize("name", NAMES)
def test_no_extrusion_leaves_its_part_footprint_by_more_than_a_bead(jobs, name):
    h = SETTINGS.layer_height_mm
    for part, tp, mesh in arm_parts(jobs[name]):
        sel = tp.extruding
        z = np.round(tp.end[sel, 2], 4)
        layers = np.unique(z)
        footprints = sections(mesh, layers - h / 2)
        starts, ends = tp.start[sel, :2], tp.end[sel, :2]
        checked = 0
        for top, footprint in zip(layers, footprints):
            on = z == top
            lines = shapely.linestrings(np.stack([starts[on], ends[on]], axis=1))
            inside = shapely.covers(footprint.buffer(W, join_style="mitre"), lines)
            assert inside.all(), "%s, layer at z=%.2f: %s leaves the part" % (
                part.arm.name, top, shapely.get_coordinates(lines[~inside][0]).tolist())
            checked += on.sum()
        assert checked == sel.sum()


@pytest.mark.parametrize("name", NAMES)
def test_the_parts_union_is_the_model(jobs, name):
    job = jobs[name]
    manifolds = [p.manifold for p in job.parts]
    union = m3.Manifold.batch_boolean(manifolds, m3.OpType.Add).volume()
    assert union == pytest.approx(job.mesh.volume, rel=1e-3)
    assert sum(m.volume() for m in manifolds) == pytest.approx(union, rel=1e-3)    # no overlap
