"""Cooperative printing with more arms, measured with `python -m ambots plan`
(every arm's firmware on one simulated clock, collisions checked): the
makespan of one model printed by 1, 2, 3 and 4 arms, as a ratio to one arm
alone (goals: 2 arms <= 0.55, 4 arms <= 0.30), and by 8 arms.

Model and cell: the beam cell (config/cells/eight_arms_beam.yaml, arms on
both sides of a 4 m beam bed, alternating sides every 0.45 m) and a beam
section of 1300 x 40 x 6 mm centred on it, printed by the arms nearest the
centre: ur10_5 alone; ur10_4 + ur10_5; + kinova_6; + kinova_3.  One arm
cannot reach the whole 3.6 m beam (config/models/beam_3600x40x6.stl), so the
8-arm run prints that beam with every arm and is compared with one arm
printing the section, scaled by length (3600 / 1300): a derived ratio."""
import os
import tempfile
import time

from ambots import data_path
from ambots.commands.plan import plan_job
from ambots.config import load_cell

CELL = "config/cells/eight_arms_beam.yaml"
SECTION_MM = (1300.0, 40.0, 6.0)
BEAM = "config/models/beam_3600x40x6.stl"
SUBSETS = [["ur10_5"], ["ur10_4", "ur10_5"], ["ur10_4", "ur10_5", "kinova_6"],
           ["kinova_3", "ur10_4", "ur10_5", "kinova_6"]]
GOALS = {2: 0.55, 4: 0.30}


def _section(folder):
    import trimesh
    path = os.path.join(folder, "beam_section.stl")
    box = trimesh.creation.box(SECTION_MM)
    box.apply_translation((0.0, 0.0, SECTION_MM[2] / 2))
    box.export(path)
    return path


def _line(n, label, rep, wall, ratio, goal=None):
    print("%d arm(s) %-34s makespan %7.0f s  ratio %s  collisions %d  min clearance %s mm  %s  wall %.0f s"
          % (n, label, rep["makespan_s"], "%.3f" % ratio + (" (goal <= %.2f)" % goal if goal else ""),
             sum(rep["collisions"].values()), rep["min_clearance_mm"],
             "finished" if rep["finished"] else "NOT finished: " + rep["reason"], wall), flush=True)


def main():
    cell = load_cell(data_path(*CELL.split("/")))
    print("cell %s; model: beam section %g x %g x %g mm (1-4 arms), %s (8 arms)"
          % ((CELL,) + SECTION_MM + (BEAM,)), flush=True)
    with tempfile.TemporaryDirectory() as folder:
        section = _section(folder)
        one = None
        for names in SUBSETS:
            t = time.perf_counter()
            rep = plan_job(section, cell, [cell.arm(n) for n in names])
            wall = time.perf_counter() - t
            if one is None:
                one = rep["makespan_s"]
            n = len(names)
            _line(n, "+".join(names), rep, wall, rep["makespan_s"] / one, GOALS.get(n))
    t = time.perf_counter()
    rep = plan_job(data_path(*BEAM.split("/")), cell, list(cell.arms))
    wall = time.perf_counter() - t
    scale = 3600.0 / SECTION_MM[0]
    _line(8, "all, whole beam (vs %.2f x 1 arm)" % scale, rep, wall, rep["makespan_s"] / (one * scale))


if __name__ == "__main__":
    main()
