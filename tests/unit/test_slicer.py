"""Slicing (ambots.slicer): the built-in back end's toolpaths, checked against
the model's own cross-sections (trimesh + shapely, independent of the
slicer's manifold3d geometry), and the prusa back end's frame.  G-code is
read with :mod:`ambots.gcode`."""
import math
import os
import re
import shutil

import numpy as np
import pytest
import shapely
import trimesh

from ambots.errors import ConfigError
from ambots.gcode import Segment, parse_gcode_text, summarize
from ambots.mesh import place_on_bed
from ambots.slicer import (DEFAULT_PRUSA_INI, BuiltinSlicer, PrusaSlicer, SliceSettings,
                           SlicerError, hatch, layer_heights, slice_mesh)

#: the model's own toolpaths, checked against its cross-sections: support off
#: (support is tested in tests/unit/test_support.py)
SETTINGS = SliceSettings(support=False)
W = SETTINGS.bead_width_mm


from shapes import MODELS, cube, overhang, sections  # tests/unit/shapes.py
NAMES = sorted(MODELS)


def placed(name, xy=(0.0, 0.0)):
    return place_on_bed(MODELS[name](), bed_center_xy_mm=xy)


class Toolpath:
    """Segments of a G-code text as arrays (mm): ``start``/``end`` (n, 3),
    ``e`` (n,), ``layer`` (n,), ``feature`` (n,) the last ``;TYPE:`` before
    the segment."""

    def __init__(self, gcode):
        self.gcode = gcode
        feature_of_line, current = [], ""
        for line in gcode.splitlines():
            if line.startswith(";TYPE:"):
                current = line[6:].strip()
            feature_of_line.append(current)
        events = list(parse_gcode_text(gcode))
        segs = [ev for ev in events if type(ev) is Segment]
        self.summary = summarize(events)
        self.start = np.array([s.start for s in segs])
        self.end = np.array([s.end for s in segs])
        self.e = np.array([s.e for s in segs])
        self.layer = np.array([s.layer for s in segs])
        self.feature = np.array([feature_of_line[s.line - 1] for s in segs])
        self.length = np.linalg.norm(self.end[:, :2] - self.start[:, :2], axis=1)
        self.extruding = (self.e > 0) & (self.length > 0)

    def filament_volume_mm3(self, settings=SETTINGS):
        s = self.summary
        return (s["extruded_filament_mm"] + s["retracted_at_end_mm"]) * settings.filament_area_mm2


_cache = {}


def gcode_of(name, backend):
    key = (name, backend)
    if key not in _cache:
        _cache[key] = Toolpath(slice_mesh(placed(name), SETTINGS, backend=backend))
    return _cache[key]


def layer_z(settings, mesh):
    """Layer tops (mm) of a model whose height is a whole number of layers."""
    h0, h = settings.first_layer_height_mm, settings.layer_height_mm
    return h0 + h * np.arange(int(round((mesh.bounds[1][2] - h0) / h)) + 1)


# ------------------------------------------------------------------ layers

def test_layer_heights():
    s = SliceSettings(first_layer_height_mm=0.3, layer_height_mm=0.2)
    z, h = layer_heights(10.0, s)
    assert z[0] == pytest.approx(0.3) and h[0] == pytest.approx(0.3)
    np.testing.assert_allclose(np.diff(z), 0.2)
    np.testing.assert_allclose(h[1:], 0.2)
    assert z[-1] == pytest.approx(9.9)        # the next one's middle, 10.0, is not below the top
    assert len(layer_heights(0.05, s)[0]) == 0


@pytest.mark.parametrize("name", NAMES)
def test_gcode_looks_like_prusaslicer_output(name):
    tp = gcode_of(name, "builtin")
    text = tp.gcode
    mesh = placed(name)
    n_layers = int(round(mesh.extents[2] / 0.2))
    for line in ("G21 ", "G90 ", "M83 "):
        assert "\n" + line in text
    assert text.count(";LAYER_CHANGE\n") == n_layers == tp.summary["layers"]
    zs = [float(z) for z in re.findall(r"^;Z:(\S+)$", text, re.M)]
    np.testing.assert_allclose(zs, 0.2 * np.arange(1, n_layers + 1), atol=1e-6)
    assert set(re.findall(r"^;HEIGHT:(\S+)$", text, re.M)) == {"0.200"}
    assert set(tp.feature[tp.extruding]) == {"External perimeter", "Perimeter",
                                             "Solid infill", "Internal infill"}
    # every layer's extrusion is at the layer's own Z
    np.testing.assert_allclose(tp.end[tp.extruding, 2], np.array(zs)[tp.layer[tp.extruding]])
    used = float(re.search(r"^; filament used \[mm\] = (\S+)$", text, re.M).group(1))
    assert used == pytest.approx(tp.summary["extruded_filament_mm"]
                                 + tp.summary["retracted_at_end_mm"], abs=0.01)
    assert not re.search(r"^\s*A\d", text, re.M) and tp.summary["a_commands"] == 0
    assert tp.summary["warnings"] == []


def test_extrusion_per_mm_is_the_bead_cross_section():
    tp = gcode_of("cube", "builtin")
    sel = tp.extruding & (tp.length > 1.0)
    h = 0.2
    area = (W - h) * h + math.pi * (h / 2) ** 2
    np.testing.assert_allclose(tp.e[sel] / tp.length[sel], area / (math.pi * 1.75 ** 2 / 4),
                               rtol=2e-3)


# ------------------------------------------------------------------ volume

def predicted_volume(mesh, s):
    """Independent estimate (shapely, on trimesh's sections at mid-layer):
    per layer a perimeter band of outline length x perimeters x bead
    spacing (a bead's cross-section / layer height: the width of material it
    lays, Slic3r's flow model), the rest filled at the infill density where
    the layers within the solid-layer counts above and below all cover it,
    solid elsewhere."""
    h = s.layer_height_mm
    spacing = W - h * (1 - math.pi / 4)
    z = layer_z(s, mesh)
    polys = sections(mesh, z - h / 2)
    n, volume = len(polys), 0.0
    for i, poly in enumerate(polys):
        perimeters = min(poly.length * s.perimeters * spacing, poly.area)
        if i - s.bottom_solid_layers < 0 or i + s.top_solid_layers >= n:
            covered = 0.0
        else:
            window = polys[i - s.bottom_solid_layers:i + s.top_solid_layers + 1]
            covered = shapely.intersection_all(window).area / poly.area
        rest = poly.area - perimeters
        volume += h * (perimeters + rest * (covered * s.infill_density + 1.0 - covered))
    return volume


@pytest.mark.parametrize("name", NAMES)
def test_extruded_volume_matches_perimeters_plus_infill(name):
    tp = gcode_of(name, "builtin")
    predicted = predicted_volume(placed(name), SETTINGS)
    assert tp.filament_volume_mm3() == pytest.approx(predicted, rel=0.10)


def test_denser_infill_extrudes_more():
    mesh = placed("cube")
    volumes = [Toolpath(BuiltinSlicer(SliceSettings(infill_density=d)).slice(mesh))
               .filament_volume_mm3() for d in (0.1, 0.4)]
    predicted = [predicted_volume(mesh, SliceSettings(infill_density=d)) for d in (0.1, 0.4)]
    assert volumes[1] - volumes[0] == pytest.approx(predicted[1] - predicted[0], rel=0.10)


# --------------------------------------------------------------- footprint

@pytest.mark.parametrize("name", NAMES)
def test_no_extrusion_leaves_the_footprint(name):
    tp = gcode_of(name, "builtin")
    mesh = placed(name)
    z = layer_z(SETTINGS, mesh)
    polys = sections(mesh, z - 0.1)
    covered = 0.0
    for i, poly in enumerate(polys):
        sel = tp.extruding & (tp.layer == i)
        pts = np.concatenate([tp.start[sel, :2], tp.end[sel, :2]])
        inside = shapely.contains_xy(poly.buffer(W, join_style="mitre"), pts[:, 0], pts[:, 1])
        assert inside.all(), "layer %d: %s outside" % (i, pts[~inside][:3])
        # and it is no thinner: the external perimeter is half a bead inside
        ext = sel & (tp.feature == "External perimeter")
        lo, hi = tp.end[ext, :2].min(axis=0), tp.end[ext, :2].max(axis=0)
        plo, phi = np.array(poly.bounds[:2]), np.array(poly.bounds[2:])
        np.testing.assert_allclose(lo, plo + W / 2, atol=0.05)
        np.testing.assert_allclose(hi, phi - W / 2, atol=0.05)
        covered += sel.sum()
    assert covered == tp.extruding.sum()


# ------------------------------------------------------------------ infill

#: longer than any link between two infill lines (sparse: 3 spacings, 6.1 mm)
LINE_MM = 7.0


def infill_angles(tp, feature, layer):
    sel = tp.extruding & (tp.feature == feature) & (tp.layer == layer) & (tp.length > LINE_MM)
    d = tp.end[sel, :2] - tp.start[sel, :2]
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180.0


def test_infill_direction_alternates():
    tp = gcode_of("cube", "builtin")
    for layer in range(0, 100):
        expected = 45.0 + 90.0 * (layer % 2)
        feature = "Solid infill" if layer < 3 or layer >= 97 else "Internal infill"
        angles = infill_angles(tp, feature, layer)
        assert len(angles) > 3
        np.testing.assert_allclose(angles, expected, atol=0.5)


def test_sparse_infill_spacing_follows_density():
    tp = gcode_of("cube", "builtin")
    sel = tp.extruding & (tp.feature == "Internal infill") & (tp.layer == 50) & (tp.length > LINE_MM)
    mid = (tp.start[sel, :2] + tp.end[sel, :2]) / 2
    offsets = np.unique(np.round(mid @ np.array([-1.0, 1.0]) / math.sqrt(2), 3))
    spacing = (W - 0.2 * (1 - math.pi / 4)) / SETTINGS.infill_density
    np.testing.assert_allclose(np.diff(offsets), spacing, atol=0.01)


def comb():
    """A bar with six teeth 4 mm wide and 2.5 mm apart (narrower than the
    sparse infill's links), and a slot along the bar: lines on both sides of
    a gap end within a link's length of each other."""
    import manifold3d as m3
    from ambots.mesh import from_manifold
    m = m3.Manifold.cube([40.0, 10.0, 6.0])
    for i in range(6):
        m = m + m3.Manifold.cube([4.0, 22.0, 6.0]).translate([i * 6.5 + 0.5, 9.0, 0.0])
    m = m - m3.Manifold.cube([30.0, 2.0, 6.0]).translate([5.0, 4.0, 0.0])
    return place_on_bed(from_manifold(m))


@pytest.mark.parametrize("name", ["cube", "hole", "comb"])
def test_sparse_infill_is_joined_and_its_links_stay_inside(name):
    """Sparse infill lines are joined by extruded links along the walls (a
    zig-zag per lane, as PrusaSlicer connects its infill) instead of a
    retracted travel each; every infill move, links included, lies inside
    the model's own cross-section (trimesh + shapely), also where lines end
    on both sides of a gap narrower than a link."""
    mesh = comb() if name == "comb" else placed(name)
    tp = Toolpath(slice_mesh(mesh, SETTINGS, backend="builtin"))
    polys = sections(mesh, layer_z(SETTINGS, mesh) - 0.1)
    sparse = tp.extruding & (tp.feature == "Internal infill")
    lines = runs = 0
    for i, poly in enumerate(polys):
        sel = np.flatnonzero((tp.extruding & np.isin(tp.feature, ["Internal infill", "Solid infill"])
                              & (tp.layer == i)))
        if not len(sel):
            continue
        segs = shapely.linestrings(np.stack([tp.start[sel, :2], tp.end[sel, :2]], axis=1))
        inside = shapely.within(segs, poly.buffer(0.01, join_style="mitre"))
        assert inside.all(), "layer %d: infill moves leave the part: %s" % (i, segs[~inside][:3])
        mine = np.flatnonzero(sparse & (tp.layer == i))
        if len(mine):
            lines += int((tp.length[mine] > LINE_MM).sum())
            # a run starts where the move before is not a sparse extrusion ending here
            cont = np.zeros(len(mine), bool)
            cont[1:] = (np.diff(mine) == 1) & np.all(tp.start[mine[1:]] == tp.end[mine[:-1]], axis=1)
            runs += int((~cont).sum())
    if name != "comb":       # its teeth are too narrow for lines longer than a link
        # one run per line before (cube 1,128 runs for 940 lines, hole 748 for 612); 94 and 102 now
        assert lines > 100
        assert runs < 0.25 * lines, "%d runs of sparse infill for %d lines" % (runs, lines)


@pytest.mark.parametrize("name,solid_layers", [
    ("cube", [0, 1, 2, 97, 98, 99]),
    ("overhang", [0, 1, 2, 50, 51, 52, 67, 68, 69]),   # 50-52: above the overhang
    ("hole", [0, 1, 2, 37, 38, 39]),
])
def test_solid_layers_at_top_bottom_and_over_overhangs(name, solid_layers):
    tp = gcode_of(name, "builtin")
    n = tp.layer.max() + 1
    has_solid = [bool((tp.extruding & (tp.layer == i) & (tp.feature == "Solid infill")).any())
                 for i in range(n)]
    has_sparse = [bool((tp.extruding & (tp.layer == i) & (tp.feature == "Internal infill")).any())
                  for i in range(n)]
    assert [i for i in range(n) if has_solid[i]] == solid_layers
    assert all(has_sparse[i] for i in range(n) if i not in solid_layers)
    if name == "overhang":
        # the bar's first layers: solid under the overhang, sparse above the stem
        assert has_sparse[50] and has_solid[50]


def test_hatch_fills_a_square_with_a_hole():
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float)
    hole = np.array([[4, 4], [4, 6], [6, 6], [6, 4]], dtype=float)    # clockwise
    segments, line = hatch([square, hole], 0.0, 0.5)
    assert np.all(segments[:, :, 1] == segments[:, :1, 1])            # horizontal
    lengths = segments[:, 1, 0] - segments[:, 0, 0]
    # line k at y = (k + 1/2) 0.5: 20 lines; the 4 through the hole are cut in two
    assert len(np.unique(line)) == 20 and len(segments) == 24
    assert lengths.sum() == pytest.approx(20 * 10 - 4 * 2)


# ------------------------------------------------------------------ travel

def test_retraction_before_long_travels():
    s = SliceSettings(z_hop_mm=0.4)
    tp = Toolpath(BuiltinSlicer(s).slice(placed("hole")))
    retracted, long_travels = 0.0, 0
    for start, end, e, length in zip(tp.start, tp.end, tp.e, tp.length):
        if length == 0 and e != 0 and start[2] == end[2]:
            retracted -= e                      # G1 E-0.8 / G1 E0.8
            assert retracted in (pytest.approx(0.0), pytest.approx(s.retract_length_mm))
        elif e > 0:
            assert retracted == pytest.approx(0.0), "extruding while retracted"
        elif length > s.retract_min_travel_mm:
            long_travels += 1
            assert retracted == pytest.approx(s.retract_length_mm), "long travel not retracted"
            assert start[2] == pytest.approx(end[2])
    assert long_travels > 40
    # z-hop: retracted travels are 0.4 mm above the layer
    text = tp.gcode
    hops = re.findall(r"^G1 Z(\S+) F\d+\nG1 X\S+ Y\S+ F\d+\nG1 Z(\S+) F", text, re.M)
    assert len(hops) >= long_travels
    assert all(float(up) - float(down) == pytest.approx(0.4) for up, down in hops)


# ------------------------------------------------------ the writer's reading

@pytest.mark.parametrize("name", NAMES)
def test_the_writers_reading_is_the_parsers(name):
    """The built-in slicer's text carries its writer's reading of it
    (:class:`ambots.sliced.SlicedText`), which the coordinator takes instead
    of parsing: it must be the parser's, segment for segment (positions,
    E as the parser adds it up, feedrates, line numbers, layers), with and
    without support, z-hop, retraction and a first layer, and on an
    arm's part cut from a whole model."""
    from ambots.coordinate.steps import read_sliced
    mesh = placed(name)
    settings = [SETTINGS, SliceSettings(support=True), SliceSettings(z_hop_mm=0.4, support=False),
                SliceSettings(retract_length_mm=0.0, support=False, first_layer_feedrate_mm_min=700.0)]
    half = place_on_bed(MODELS[name]()).slice_plane([0, 0, 0], [1, 0, 0], cap=True)
    texts = [slice_mesh(mesh, s) for s in settings]
    texts.append(slice_mesh(half, SliceSettings(support=True), whole=mesh, keep=[((1.0, 0.0, 0.0), 0.0)]))
    for text in texts:
        assert text.layers is not None
        handed, parsed = read_sliced(text, "x.gcode"), read_sliced(str(text), "x.gcode")
        assert handed == parsed
        assert sum(len(v) for v in parsed.layers.values()) > 200


def test_a_reading_that_may_differ_from_the_text_is_given_up():
    """The writer's reading is dropped, so that the text is parsed, when
    its line or G1 count is not the text's or a number is beyond the
    parser's limit."""
    from ambots.sliced import MoveRecord
    text = slice_mesh(placed("cube"), SETTINGS)
    ok = MoveRecord()
    ok.text("; a\n")
    ok.move("1.000", "2.000", None, None, "1200")
    assert ok.layers("; a\nG1 X1.000 Y2.000 F1200\n") == {0: [Segment((0.0, 0.0, 0.0), (1.0, 2.0, 0.0), 0.0,
                                                                         1200.0, False, 2, -1)]}
    for other in ("; a\nG1 X1.000 Y2.000 F1200\nG1 X3\n",        # a G1 line it did not write
                  "; a\r; b\nG1 X1.000 Y2.000 F1200\n"):            # a line break the parser counts
        rec = MoveRecord()
        rec.text("; a\n")
        rec.move("1.000", "2.000", None, None, "1200")
        assert rec.layers(other) is None
    far = MoveRecord()
    far.move("2000000.000", None, None, None, "1200")
    assert far.layers("G1 X2000000.000 F1200\n") is None
    assert text.layers is not None and str(text) == text


# ----------------------------------------------------------------- refusals

def test_settings_are_checked():
    with pytest.raises(ConfigError, match="layer_height_mm: must be > 0"):
        SliceSettings(layer_height_mm=-0.2)
    with pytest.raises(ConfigError, match="infill_density: must be within 0..1"):
        SliceSettings(infill_density=20)
    with pytest.raises(ConfigError, match="perimeters: must be a whole number"):
        SliceSettings(perimeters=1.5)
    with pytest.raises(ConfigError, match="bead_width_mm: must be a finite number"):
        SliceSettings(bead_width_mm=float("nan"))


def test_unslicable_models_are_refused():
    with pytest.raises(SlicerError, match="unknown slicer back end 'cura'"):
        slice_mesh(placed("cube"), backend="cura")
    sunk = placed("cube")
    sunk.apply_translation((0, 0, -1.0))
    with pytest.raises(SlicerError, match="1.000 mm below the bed"):
        slice_mesh(sunk)
    with pytest.raises(SlicerError, match="nothing to print"):
        slice_mesh(place_on_bed(trimesh.creation.box((10, 10, 0.05))))


# ------------------------------------------------------------------- prusa

@pytest.mark.parametrize("name", NAMES)
def test_prusa_gcode_reads_and_shares_the_frame(name):
    prusa, builtin = gcode_of(name, "prusa"), gcode_of(name, "builtin")
    assert prusa.summary["warnings"] == []
    assert prusa.summary["layers"] == builtin.summary["layers"]
    np.testing.assert_allclose(prusa.summary["bbox_mm"], builtin.summary["bbox_mm"], atol=W)
    # same settings, roughly the same material: PrusaSlicer adds infill anchors
    # and prints bridges with thick beads (+30 % on the overhang)
    predicted = predicted_volume(placed(name), SETTINGS)
    assert prusa.filament_volume_mm3() == pytest.approx(predicted, rel=0.35)


def test_prusa_keeps_an_off_centre_placement():
    mesh = placed("overhang", xy=(37.5, -61.0))
    boxes = [Toolpath(slice_mesh(mesh, SETTINGS, backend=b)).summary["bbox_mm"]
             for b in ("builtin", "prusa")]
    np.testing.assert_allclose(boxes[0], boxes[1], atol=W)
    np.testing.assert_allclose(np.mean(np.array(boxes[1])[:, :2], axis=0), [37.5, -61.0], atol=W)


def test_prusa_with_awkward_file_names(tmp_path, monkeypatch):
    canary = tmp_path / "pwned"   # created if a shell ever ran a name
    monkeypatch.setenv("CANARY", str(canary))
    folder = tmp_path / "dir with spaces; $(touch $CANARY) & 'q' \"dq\""
    folder.mkdir()
    ini = folder / "my config; rm -rf ~ `id`.ini"
    shutil.copyfile(DEFAULT_PRUSA_INI, str(ini))
    stl = folder / "cube \"20\" $HOME | * [a] {b} `touch $CANARY`.stl"
    placed("cube").export(str(stl))
    out = folder / "out; echo 'x' > y & .gcode"
    PrusaSlicer(SETTINGS, ini_path=ini).slice_file(stl, out)
    assert Toolpath(out.read_text()).summary["layers"] == 100
    assert sorted(os.listdir(folder)) == sorted([ini.name, stl.name, out.name])
    assert not canary.exists()


def test_prusa_errors_carry_its_message(tmp_path):
    bad = tmp_path / "not really.stl"
    bad.write_bytes(b"\x01" * 500)
    with pytest.raises(SlicerError, match=r"(?s)not really\.stl: prusa-slicer failed.*"
                                          r"Loading of a model file failed"):
        PrusaSlicer(SETTINGS).slice_file(bad, tmp_path / "out.gcode")
    ini = tmp_path / "broken.ini"
    ini.write_text("layer_height = banana\n")
    with pytest.raises(SlicerError, match="Invalid value provided for parameter layer_height"):
        PrusaSlicer(SETTINGS, ini_path=ini).slice(placed("cube"))
    with pytest.raises(SlicerError, match="'no-such-slicer' not found"):
        PrusaSlicer(SETTINGS, executable="no-such-slicer").slice(placed("cube"))
