"""Benchmark of the built-in slicer against prusa-slicer (run by
``tests/bench/run.py``, or alone).

Both back ends slice the same placed models with the same
:class:`~ambots.slicer.SliceSettings` (0.2 mm layers) through the same call,
:func:`ambots.slicer.slice_mesh`, in this one run: the prusa time therefore
includes writing the temporary STL, starting the program and reading its
G-code back, the price a user pays for it.  Each time is the best of
``REPEAT`` runs.  Goal: builtin/prusa <= 1.0 on every model.
"""
import os
import time

import manifold3d as m3
import trimesh

from ambots.mesh import from_manifold, place_on_bed
from ambots.slicer import SliceSettings, slice_mesh

REPEAT = 3
GOAL = 1.0


def models():
    """Name -> trimesh.Trimesh (mm), placed on the bed at (0, 0)."""
    shapes = {
        "cube20": trimesh.creation.box((20.0, 20.0, 20.0)),
        "cylinder40": trimesh.creation.cylinder(radius=20.0, height=40.0, sections=128),
        "overhang": from_manifold(m3.Manifold.cube([12, 12, 30]).translate([-6, -6, 0])
                                  + m3.Manifold.cube([60, 12, 8]).translate([-30, -6, 30])),
        "hole": from_manifold(m3.Manifold.cube([50, 50, 30]).translate([-25, -25, 0])
                              - m3.Manifold.cylinder(40, 8, 8, 48).translate([0, 0, -5])),
        "sphere50": trimesh.creation.icosphere(subdivisions=5, radius=25.0),
    }
    return {name: place_on_bed(mesh) for name, mesh in shapes.items()}


def best_time(fn, repeat=REPEAT):
    """Shortest wall time (s) of ``repeat`` calls of ``fn`` and its last result."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main():
    settings = SliceSettings()
    print("slicer: layer height %.2f mm, best of %d, %d CPUs (prusa-slicer may use several, "
          "builtin uses one)" % (settings.layer_height_mm, REPEAT, os.cpu_count()))
    total_b = total_p = 0.0
    worst = 0.0
    for name, mesh in models().items():
        tb, gb = best_time(lambda: slice_mesh(mesh, settings, backend="builtin"))
        tp, gp = best_time(lambda: slice_mesh(mesh, settings, backend="prusa"))
        total_b, total_p, worst = total_b + tb, total_p + tp, max(worst, tb / tp)
        print("slicer %s: builtin %.3f s, prusa %.3f s, ratio builtin/prusa = %.2f "
              "(%d faces; %d / %d G-code lines)"
              % (name, tb, tp, tb / tp, len(mesh.faces), gb.count("\n"), gp.count("\n")))
    print("slicer total: builtin %.3f s, prusa %.3f s, ratio builtin/prusa = %.2f; worst %.2f "
          "(goal <= %.1f: %s)" % (total_b, total_p, total_b / total_p, worst, GOAL,
                                  "met" if worst <= GOAL else "NOT met"))


if __name__ == "__main__":
    main()
