"""``python -m ambots cell``: check a cell and write its descriptions."""
import os


def register(sub):
    p = sub.add_parser("cell", help="check a cell config; write its URDF / RViz config",
                       description="Load and check a cell (arms, base poses, bed), print a summary "
                                   "and the bed corners each arm can reach with the nozzle down.")
    p.add_argument("--cell", default=None, help="cell YAML (default: config/cells/kinova_ur10.yaml)")
    p.add_argument("--urdf", metavar="FILE", help="write the whole cell's URDF to FILE ('-' for stdout)")
    p.add_argument("--rviz", metavar="FILE", help="write an RViz config for the cell to FILE")
    p.set_defaults(func=run)


def run(args):
    import numpy as np

    from ambots.config import default_cell_path, load_cell
    from ambots.model import arm_kinematics, cell_urdf
    from ambots.rviz import rviz_config
    from ambots.workspace import bed_reachability

    cell = load_cell(args.cell or default_cell_path())
    if args.urdf:
        text = cell_urdf(cell)
        if args.urdf == "-":
            print(text)
            return 0
        _write(args.urdf, text)
    if args.rviz:
        _write(args.rviz, rviz_config(cell))
    print("cell %s (%s): bed %.3f x %.3f m, top centre at (%.3f, %.3f, %.3f) m" %
          ((cell.name, cell.path) + cell.bed.size[:2] + cell.bed.xyz))
    for arm in cell.arms:
        kin = arm_kinematics(arm)
        reach = bed_reachability(cell, arm, kin)
        print("  R%d %-10s %-12s base (%.3f, %.3f, %.3f) m yaw %.1f deg, %d joints; "
              "reaches %d/%d bed test points (nozzle down)" %
              (arm.id, arm.name, arm.profile.name, *arm.base_xyz, np.degrees(arm.base_rpy[2]),
               kin.dof, reach.sum(), reach.size))
    return 0


def _write(path, text):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)
