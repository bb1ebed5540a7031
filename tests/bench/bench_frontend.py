"""The front end's time from a model to per-arm programs, side by side with
``prusa-slicer`` alone on the same model, in one run (issue "Cooperation
pays", item 4; goal: the whole job no slower than prusa-slicer alone).

The model: a 327,680-triangle sphere (icosphere, 5 subdivisions more than
bench_slicer's), 60 mm across, so that the mesh's size matters.  Timed:
``prusa-slicer`` on the placed model (through ``slice_mesh``, the way the
job calls it: temporary STL, program start, G-code read back); the whole
job as the menu runs it (``run_job``: model, split, slicing, coordination,
and the planner's timing of the plans it compares) with the built-in slicer,
for the default cell; and the same with the arms given (``--arms``: one
plan, still timed)."""
import os
import tempfile
import time

import trimesh

from ambots.config import default_cell_path, load_cell
from ambots.job import run_job
from ambots.mesh import place_on_bed
from ambots.slicer import SliceSettings, slice_mesh


def main():
    cell = load_cell(default_cell_path())
    mesh = place_on_bed(trimesh.creation.icosphere(subdivisions=7, radius=30.0))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "sphere60.stl")
        mesh.export(path)
        t = time.perf_counter()
        slice_mesh(mesh, SliceSettings(), backend="prusa")
        prusa = time.perf_counter() - t
        t = time.perf_counter()
        job = run_job(path, cell)
        chosen = time.perf_counter() - t
        t = time.perf_counter()
        run_job(path, cell, list(cell.arms))
        forced = time.perf_counter() - t
    print("front end, %d triangles: prusa-slicer alone %.1f s; the job (builtin slicer) with the planner's "
          "choice %.1f s (%s chosen) = %.1fx; both arms given %.1f s = %.1fx (goal <= 1.0x)"
          % (len(mesh.faces), prusa, chosen, "+".join(job.chosen.arms), chosen / prusa, forced, forced / prusa),
          flush=True)


if __name__ == "__main__":
    main()
