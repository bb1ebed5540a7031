"""Support in the built-in slicer (ambots.support), measured on the G-code by
the independent mid-air rule of issue "Printable" (tests/unit/unsupported_rule.py:
its own parser, samples and a k-d tree; not the slicer's detector), and
checked against the models' own cross-sections (trimesh + shapely)."""
import re

import manifold3d as m3
import numpy as np
import pytest
import shapely

from ambots.errors import ConfigError
from ambots.mesh import from_manifold, load_model, place_on_bed
from ambots.slicer import PrusaSlicer, SliceSettings, slice_mesh
from ambots.support import SUPPORT, SUPPORT_INTERFACE

from shapes import overhang, sections  # tests/unit/shapes.py
from unsupported_rule import extrusion_paths, unsupported_share

ON, OFF = SliceSettings(), SliceSettings(support=False)
W = ON.bead_width_mm


def box(x0, y0, z0, x1, y1, z1):
    return m3.Manifold.cube([x1 - x0, y1 - y0, z1 - z0]).translate([x0, y0, z0])


def figure():
    """A small figure: two legs 14 mm apart, a body, arms sticking out 10 mm, a head."""
    return from_manifold(box(-13, -4, 0, -7, 4, 10) + box(7, -4, 0, 13, 4, 10) + box(-15, -5, 10, 15, 5, 20)
                         + box(-25, -2, 15, -15, 2, 19) + box(15, -2, 15, 25, 2, 19) + box(-3, -3, 20, 3, 3, 25))


def bridge(gap):
    """Two pillars ``gap`` mm apart under a slab."""
    return from_manifold(box(-gap / 2 - 6, -5, 0, -gap / 2, 5, 6) + box(gap / 2, -5, 0, gap / 2 + 6, 5, 6)
                         + box(-gap / 2 - 6, -5, 6, gap / 2 + 6, 5, 9))


def table():
    """A 200 mm beam on two legs 160 mm apart: its overhang spans the seam of a two-arm cell."""
    return from_manifold(box(-100, -10, 0, -80, 10, 12) + box(80, -10, 0, 100, 10, 12) + box(-100, -10, 12, 100, 10, 16))


MODELS = {"T": overhang, "figure": figure}
_cache = {}


def sliced(name, settings=ON, backend="builtin"):
    key = (name, settings, backend)
    if key not in _cache:
        _cache[key] = slice_mesh(MODELS[name](), settings, backend=backend)
    return _cache[key]


def feature_points(gcode, features):
    """(n, 3) ends of the extruding moves of ``features`` (;TYPE: names), mm."""
    out, current, x, y, z = [], None, 0.0, 0.0, 0.0
    for line in gcode.splitlines():
        if line.startswith(";TYPE:"):
            current = line[6:].strip()
            continue
        words = dict(re.findall(r"([XYZE])(-?\d*\.?\d+)", line.split(";")[0]))
        if not line.startswith("G1"):
            continue
        x, y, z = float(words.get("X", x)), float(words.get("Y", y)), float(words.get("Z", z))
        if current in features and float(words.get("E", 0)) > 0 and ("X" in words or "Y" in words):
            out.append((x, y, z))
    return np.array(out).reshape(-1, 3)


# ------------------------------------------------------------ mid-air share

@pytest.mark.parametrize("name", sorted(MODELS))
def test_support_leaves_no_extrusion_in_mid_air(name):
    with_support = unsupported_share(sliced(name, ON))[0]
    without = unsupported_share(sliced(name, OFF))[0]
    print("%s: unsupported share %.4f %% with support, %.3f %% without" % (name, 100 * with_support, 100 * without))
    assert without > 0.01          # the rule sees the overhangs: it does not pass vacuously
    assert with_support <= 0.001
    assert SUPPORT in sliced(name, ON) and SUPPORT_INTERFACE in sliced(name, ON)


def test_the_rule_counts_a_cantilever_by_hand():
    """The rule itself, on a hand-made toolpath: a 10 mm line on layer 0 and a
    20 mm line on layer 1 that runs 10 mm past its end: all but one bead width of that is unsupported;
    a 4 mm gap between two supported stretches is a bridge."""
    g = ("G1 Z0.2\nG1 X0 Y0\nG1 X10 Y0 E1\nG1 Z0.4\nG1 X0 Y0\nG1 X20 Y0 E1\n")
    share, lost, total = unsupported_share(g)
    assert total == pytest.approx(30.0) and lost == pytest.approx(10.0 - W, abs=0.2)   # a bead width of it is carried
    g = ("G1 Z0.2\nG1 X0 Y0\nG1 X5 Y0 E1\nG1 X9 Y0\nG1 X14 Y0 E1\nG1 Z0.4\nG1 X0 Y0\nG1 X14 Y0 E1\n")
    assert unsupported_share(g)[1] == pytest.approx(0.0)


# ------------------------------------------------------------ where it goes

def test_support_is_clear_of_the_model_and_under_its_overhang():
    mesh = MODELS["T"]()
    g = sliced("T", ON)
    pts = feature_points(g, {SUPPORT, SUPPORT_INTERFACE})
    assert len(pts)
    zs = np.unique(np.round(pts[:, 2], 3))
    above = shapely.union_all(sections(mesh, [10.1, 12.0]))      # the bar, seen from below
    for z, sec in zip(zs, sections(mesh, zs - 0.05)):
        p = pts[np.isclose(pts[:, 2], z)]
        d = shapely.distance(sec, shapely.points(p[:, :2])) if not sec.is_empty else np.full(len(p), np.inf)
        # the bead (half a width either side) stays support_xy_gap_mm off the model
        assert d.min() >= ON.support_xy_gap_mm + W / 2 - 0.02, z
        assert shapely.contains_xy(above.buffer(0.01), p[:, 0], p[:, 1]).all(), z
    # z gap: the support's top is support_z_gap_mm under the bar's bottom (z = 10 mm)
    assert pts[:, 2].max() == pytest.approx(10.0 - ON.support_z_gap_mm, abs=1e-3)
    # ... and the lowest extrusion of the bar beside the stem is on the layer right above it
    bar = feature_points(g, {"External perimeter", "Perimeter", "Solid infill"})
    assert bar[np.abs(bar[:, 0]) > 4.0, 2].min() == pytest.approx(10.0 + ON.layer_height_mm, abs=1e-3)


def test_support_stops_on_the_part_below():
    """An overhang over a lower step of the model: the support stands on the
    step (none under it, no point inside the model)."""
    mesh = from_manifold(box(-10, -5, 0, 10, 5, 4) + box(-10, -5, 4, -4, 5, 10) + box(-10, -5, 10, 10, 5, 12))
    g = slice_mesh(mesh, ON)
    pts = feature_points(g, {SUPPORT, SUPPORT_INTERFACE})
    assert len(pts) and pts[:, 2].min() > 4.0      # on the step, not down to the bed
    assert unsupported_share(g)[0] <= 0.001 < unsupported_share(slice_mesh(mesh, OFF))[0]


@pytest.mark.parametrize("gap", [6.0, 16.0])
def test_a_short_bridge_gets_no_support(gap):
    mesh = bridge(gap)
    g = slice_mesh(mesh, ON)
    n = len(feature_points(g, {SUPPORT, SUPPORT_INTERFACE}))
    if gap <= ON.bridge_max_mm:
        assert n == 0
        assert unsupported_share(g)[0] <= 0.001     # and the rule agrees: it is a bridge
    else:
        assert n > 0
        assert unsupported_share(g)[0] <= 0.001 < unsupported_share(slice_mesh(mesh, OFF))[0]


# ------------------------------------------------------------ on and off

def test_no_overhang_no_support_and_the_demo_block_is_unchanged():
    from ambots import data_path
    mesh = place_on_bed(load_model(data_path("config", "models", "demo_block.stl")))
    on, off = slice_mesh(mesh, ON), slice_mesh(mesh, OFF)
    # the same toolpath (only the header's list of settings differs)
    code = lambda t: [ln for ln in t.splitlines() if not re.match(r"; \w+ = ", ln)]
    assert code(on) == code(off)
    assert "Support" not in on


def test_support_off_prints_none():
    g = sliced("T", OFF)
    assert "Support" not in g.replace("; support", "")
    assert len(feature_points(g, {SUPPORT, SUPPORT_INTERFACE})) == 0


@pytest.mark.parametrize("field,value", [("support", 1), ("support_angle_deg", 90), ("support_angle_deg", 0),
                                         ("support_interface_layers", 0), ("support_z_gap_mm", 0.2),
                                         ("support_xy_gap_mm", -1), ("support_spacing_mm", 0.1),
                                         ("bridge_max_mm", -1)])
def test_support_settings_are_checked(field, value):
    with pytest.raises(ConfigError, match=field):
        SliceSettings(**{field: value})


# ------------------------------------------------------------ the job's parts

def test_each_arm_prints_the_support_of_its_own_part():
    """The table's overhang spans the seam of the default cell: each arm's
    part gets support inside its prism only, and the two programs together
    leave nothing in mid-air by the rule."""
    from ambots.config import default_cell_path, load_cell
    from ambots.job import slice_parts, split
    cell = load_cell(default_cell_path())
    whole = place_on_bed(table())
    parts = split(whole, cell, cell.arms)
    texts = slice_parts(parts, "builtin", ON, whole)
    assert len(texts) == 2
    for part in parts:
        pts = feature_points(texts[part.arm.name], {SUPPORT, SUPPORT_INTERFACE})
        assert len(pts) > 100, part.arm.name
        for n, off in part.planes:
            assert (pts[:, :2] @ np.asarray(n)[:2] >= off - 1e-3).all(), part.arm.name
    both = "\n".join(texts.values())
    assert unsupported_share(both)[0] <= 0.001
    alone = "\n".join(slice_parts(parts, "builtin", OFF, whole).values())
    assert unsupported_share(alone)[0] > 0.01


# ------------------------------------------------------------ prusa

def test_prusa_gets_the_support_setting():
    args = PrusaSlicer(SliceSettings(support_angle_deg=30)).settings_args()
    i = args.index("--support-material-threshold")
    assert "--support-material" in args and float(args[i + 1]) == 60.0   # PrusaSlicer: from the horizontal
    assert "--no-support-material" in PrusaSlicer(OFF).settings_args()


def test_prusa_prints_support_when_asked():
    on, off = sliced("figure", ON, "prusa"), sliced("figure", OFF, "prusa")
    assert len(feature_points(on, {SUPPORT, SUPPORT_INTERFACE})) > 0
    assert len(feature_points(off, {SUPPORT, SUPPORT_INTERFACE})) == 0
    print("prusa figure: unsupported share %.3f %% with support, %.3f %% without"
          % (100 * unsupported_share(on)[0], 100 * unsupported_share(off)[0]))
    assert extrusion_paths(on)
