"""IK solves per second along a straight 1 m line of nozzle poses at 0.1 mm
spacing (10,001 poses, nozzle down), for each arm: our path IK against plain
PyKDL ChainIkSolverPos_LMA solving the same poses one by one (each seeded by
the previous solution, target orientation = the nozzle-down orientation of the
first pose), measured side by side in one run."""
import time

import numpy as np
import PyKDL as kdl

from ambots.config import load_arm_profile
from ambots.kinematics import kdl_chain
from ambots.model import arm_kinematics

# a 1 m line each arm can follow with the nozzle down (base frame, m)
LINES = {"ur10": ([0.45, -0.5, 0.2], [0.45, 0.5, 0.2]),
         "kinova_gen3": ([0.30, -0.5, 0.15], [0.30, 0.5, 0.15])}


def lma_baseline(kin, P, seed, R):
    chain = kdl_chain(kin.chain)
    solver = kdl.ChainIkSolverPos_LMA(chain)
    q_in, q_out = kdl.JntArray(kin.dof), kdl.JntArray(kin.dof)
    for i, v in enumerate(seed):
        q_in[i] = float(v)
    rot = kdl.Rotation(*R.ravel().tolist())
    ok = 0
    t = time.perf_counter()
    for p in P:
        if solver.CartToJnt(q_in, kdl.Frame(rot, kdl.Vector(*p)), q_out) >= 0:
            ok += 1
            q_in, q_out = q_out, q_in
    return time.perf_counter() - t, ok


def main():
    for name, (a, b) in LINES.items():
        prof = load_arm_profile("config/arms/%s.yaml" % name)
        kin = arm_kinematics(prof)
        P = np.linspace(a, b, 10001)
        q0 = kin.ik(P[0], prof.home)
        t = time.perf_counter()
        Q, ok = kin.ik_path(P, q0)
        ours = time.perf_counter() - t
        err = np.linalg.norm(kin.fk_batch(Q)[:, :3, 3] - P, axis=1).max()
        base, base_ok = lma_baseline(kin, P, q0, kin.fk(q0)[:3, :3])
        print("ik %-12s %d poses: ours %.3f s (%.0f solves/s, %d ok, max err %.1e m); "
              "KDL LMA %.3f s (%.0f solves/s, %d ok); speed-up ours/LMA = %.1fx"
              % (name, len(P), ours, len(P) / ours, ok.sum(), err, base, len(P) / base, base_ok, base / ours),
              flush=True)


if __name__ == "__main__":
    main()
