"""Benchmark of slicing with support: the built-in slicer against
prusa-slicer with its automatic support (run by ``tests/bench/run.py``, or
alone).

Both back ends slice the same placed models with the same
:class:`~ambots.slicer.SliceSettings` (support on, 45 deg, the same z and xy
gaps passed through) through :func:`ambots.slicer.slice_mesh`, in this one
run; each time is the best of ``REPEAT`` runs.  The unsupported share of each
G-code is measured by the independent rule of tests/unit/unsupported_rule.py
(layer slabs of the nominal grid, one bead width, bridges up to 10 mm).
PrusaSlicer prints its support on layers of its own heights when the
contact distance is not 0, so by that rule much of its support layers
carry nothing; the figure with ``--support-material-contact-distance 0
--support-material-synchronize-layers`` (support on the object's layers,
no gap) is shown beside it.
"""
import os
import sys

import manifold3d as m3

from ambots.gcode import parse_gcode_text
from ambots.mesh import from_manifold, place_on_bed
from ambots.overhang import unsupported_extrusion
from ambots.slicer import PrusaSlicer, SliceSettings, slice_mesh

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "unit"))
from unsupported_rule import unsupported_share  # noqa: E402
from bench_slicer import best_time  # noqa: E402

REPEAT = 3


def box(x0, y0, z0, x1, y1, z1):
    return m3.Manifold.cube([x1 - x0, y1 - y0, z1 - z0]).translate([x0, y0, z0])


def models():
    """Name -> placed trimesh (mm): the figure with legs of tests/unit/test_support.py
    and a T whose bar overhangs 24 mm on each side."""
    figure = (box(-13, -4, 0, -7, 4, 10) + box(7, -4, 0, 13, 4, 10) + box(-15, -5, 10, 15, 5, 20)
              + box(-25, -2, 15, -15, 2, 19) + box(15, -2, 15, 25, 2, 19) + box(-3, -3, 20, 3, 3, 25))
    tee = box(-6, -6, 0, 6, 6, 30) + box(-30, -6, 30, 30, 6, 38)
    return {"figure": place_on_bed(from_manifold(figure)), "T": place_on_bed(from_manifold(tee))}


def main():
    settings = SliceSettings(support=True)
    print("support: layer height %.2f mm, support under > %g deg from vertical, z gap %g mm, best of %d, "
          "%d CPUs" % (settings.layer_height_mm, settings.support_angle_deg, settings.support_z_gap_mm,
                       REPEAT, os.cpu_count()))
    synced = ("--support-material-contact-distance", "0", "--support-material-synchronize-layers")
    for name, mesh in models().items():
        tb, gb = best_time(lambda: slice_mesh(mesh, settings, backend="builtin"), REPEAT)
        tp, gp = best_time(lambda: slice_mesh(mesh, settings, backend="prusa"), REPEAT)
        gs = PrusaSlicer(settings, extra_args=synced).slice(mesh)
        off = slice_mesh(mesh, SliceSettings(support=False), backend="builtin")
        window = unsupported_extrusion([parse_gcode_text(gp)])["unsupported_share"]
        print("support %s: builtin %.3f s, prusa %.3f s, ratio builtin/prusa = %.2f; unsupported share "
              "builtin %.3f %% (no support: %.3f %%), prusa %.3f %% (ambots.overhang's height window: %.3f %%; "
              "contact 0, synchronized: %.3f %%)"
              % (name, tb, tp, tb / tp, 100 * unsupported_share(gb)[0], 100 * unsupported_share(off)[0],
                 100 * unsupported_share(gp)[0], 100 * window, 100 * unsupported_share(gs)[0]))


if __name__ == "__main__":
    main()
