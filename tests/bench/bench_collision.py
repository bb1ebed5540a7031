"""Collision checks per second in the default cell: arm-arm clearance
(every capsule pair) and arm-bed clearance at 10,000 random simultaneous
configurations, the seam-zone computation, and the mesh of 100,000 beads."""
import time

import numpy as np

from ambots.collision import ArmBody, bed_clearance, clearance_between, seam_zone
from ambots.config import default_cell_path, load_cell
from ambots.deposit import Deposit


def random_configs(body, n, rng):
    lo = np.where(np.isfinite(body.kin.lower), body.kin.lower, -np.pi)
    hi = np.where(np.isfinite(body.kin.upper), body.kin.upper, np.pi)
    return rng.uniform(lo, hi, (n, body.kin.dof))


def timed(f, *args):
    t = time.perf_counter()
    out = f(*args)
    return out, time.perf_counter() - t


def main():
    cell = load_cell(default_cell_path())
    a, b = (ArmBody.from_arm(arm) for arm in cell.arms)
    rng = np.random.default_rng(0)
    n = 10_000
    QA, QB = random_configs(a, n, rng), random_configs(b, n, rng)
    c, dt = timed(clearance_between, a, QA, b, QB)
    print("clearance_between %d configs x %d capsule pairs: %.3f s (%.0f configs/s, %.1f%% colliding)"
          % (n, len(a) * len(b), dt, n / dt, 100.0 * np.mean(c < 0)), flush=True)
    c, dt = timed(bed_clearance, b, QB, cell)
    print("bed_clearance %d configs x %d capsules: %.3f s (%.0f configs/s)" % (n, len(b) - 1, dt, n / dt), flush=True)
    z, dt = timed(seam_zone, cell)
    print("seam_zone: facing %.1f mm, any direction %.1f mm (%.2f s)" % (z.facing_mm, z.any_mm, dt), flush=True)
    k = 100_000
    s = rng.uniform(-0.1, 0.1, (k, 3))
    dep = Deposit()
    dep.add("ur10", s, s + rng.normal(scale=1e-3, size=(k, 3)) * [1, 1, 0], 9e-8, 2e-4)
    mesh, dt = timed(dep.to_mesh, {"ur10": (0.1, 0.45, 0.95)})
    print("Deposit.to_mesh %d beads -> %d faces: %.3f s" % (k, len(mesh.faces), dt), flush=True)


if __name__ == "__main__":
    main()
