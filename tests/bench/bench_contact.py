"""The continuous contact check (ambots.contact) on the demo's executed motion
(`python -m ambots plan` of the demo block, both arms): samples evaluated,
throughput (samples/s), the closest approach and its provable lower bound,
side by side with the former check (every 0.1 s of simulated time, which let
a travel at 150 mm/s move 15 mm between samples)."""
import time

import numpy as np

from ambots import data_path
from ambots.collision import ArmBody, clearance_between
from ambots.config import default_cell_path, load_cell
from ambots.contact import RESOLUTION_M
from ambots.job import DEMO_MODEL, run_job
from ambots.sim import _trace, check_motion, simulate


def main():
    cell = load_cell(default_cell_path())
    job = run_job(data_path(*DEMO_MODEL.split("/")), cell, list(cell.arms))
    result = simulate(job.programs, cell)
    t = time.perf_counter()
    m = check_motion(result, cell)
    dt = time.perf_counter() - t
    print("continuous check (%.0f mm resolution): %d samples in %.1f s = %.0f samples/s; contacts %s; closest "
          "approach %.2f mm, provable bound %.2f mm; bed %.2f mm (bound %.2f), part %.2f mm (bound %.2f)"
          % (RESOLUTION_M * 1000, m["samples"], dt, m["samples"] / dt, m["collisions"], m["min_clearance_mm"],
             m["bound_mm"]["arm_arm"], m["min_bed_clearance_mm"], m["bound_mm"]["arm_bed"],
             m["min_part_clearance_mm"], m["bound_mm"]["arm_part"]), flush=True)
    # the former fixed grid, arm-arm only, for comparison
    names = list(result.runners)
    traces = {n: _trace(result.runners[n]) for n in names}
    t_end = max(float(tr[0][-1]) for tr in traces.values())
    grid = np.arange(0.0, t_end + 0.1, 0.1)
    Q = {n: np.stack([np.interp(grid, traces[n][0], traces[n][1][:, j]) for j in range(traces[n][1].shape[1])],
                     axis=1) for n in names}
    bodies = {a.name: ArmBody.from_arm(a) for a in cell.arms}
    t = time.perf_counter()
    c = clearance_between(bodies[names[0]], Q[names[0]], bodies[names[1]], Q[names[1]])
    dt = time.perf_counter() - t
    print("former 0.1 s grid, arm-arm: %d samples in %.1f s = %.0f samples/s; closest approach %.2f mm "
          "(no bound between samples)" % (len(grid), dt, len(grid) / dt, c.min() * 1000), flush=True)


if __name__ == "__main__":
    main()
