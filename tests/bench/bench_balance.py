"""Print-time balance between the arms of the default cell: longest / shortest
program print time (at programmed feedrates) after the partition, for a few
models, built-in slicer (goal <= 1.10)."""
import os
import tempfile

import trimesh

from ambots.config import default_cell_path, load_cell
from ambots.job import run_job


def models():
    box = trimesh.creation.box([60, 40, 10])
    cyl = trimesh.creation.cylinder(25, 15, sections=96)
    ell = trimesh.boolean.union([trimesh.creation.box([60, 15, 10]),
                                 trimesh.creation.box([15, 50, 10]).apply_translation([-22.5, 17.5, 0])],
                                engine="manifold")
    return {"box60x40": box, "cylinder50": cyl, "L-shape": ell}


def main():
    cell = load_cell(default_cell_path())
    with tempfile.TemporaryDirectory() as tmp:
        for name, mesh in models().items():
            path = os.path.join(tmp, name + ".stl")
            mesh.export(path)
            s = run_job(path, cell, list(cell.arms)).summary()     # both arms: the balance of the split
            times = [a["print_time_s"] for a in s["arms"].values()]
            print("balance %-10s print time per arm %s s; longest/shortest = %.3f (goal <= 1.10)"
                  % (name, ", ".join("%.0f" % t for t in times), max(times) / min(times)), flush=True)


if __name__ == "__main__":
    main()
