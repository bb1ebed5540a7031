"""``python -m ambots cell``: check a cell and write its descriptions."""
import os


def register(sub):
    p = sub.add_parser("cell", help="check a cell config; write its URDF / RViz config",
                       description="Load and check a cell (arms, base poses, bed), print a summary, "
                                   "how many bed test points each arm can reach with the nozzle down and, "
                                   "with several arms, how much of its own share of the bed (its part "
                                   "when the whole bed is split among the arms like a model) it reaches.")
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
    share = _shares(cell) if len(cell.arms) > 1 else None
    for i, arm in enumerate(cell.arms):
        kin = arm_kinematics(arm)
        reach = bed_reachability(cell, arm, kin)
        line = ("  R%d %-10s %-12s inbox %s, base (%.3f, %.3f, %.3f) m yaw %.1f deg, %d joints; "
                "reaches %d/%d bed test points (nozzle down)" %
                (arm.id, arm.name, arm.profile.name, arm.inbox, *arm.base_xyz, np.degrees(arm.base_rpy[2]),
                 kin.dof, reach.sum(), reach.size))
        if share is not None:
            pts = share[1][share[0] == i]
            ok = bed_reachability(cell, arm, kin, pts)
            line += ", %d/%d of its share" % (ok.sum(), ok.size)
        print(line)
    return 0


def _shares(cell, n=21):
    """Each arm's share of the bed: the part it gets when the whole bed (a
    1 mm slab) is split among the arms as a model would be
    (:func:`ambots.partition.partition`, balanced), sampled on an n x n grid
    at the bed's top and at its printable height.  Returns (owner index (N,),
    world points (N, 3)); -1 for a point on no part."""
    import manifold3d as m3
    import numpy as np

    from ambots.partition import partition
    from ambots.workspace import bed_points
    sx, sy = cell.bed.size[0] * 1000.0, cell.bed.size[1] * 1000.0
    slab = m3.Manifold.cube([sx, sy, 1.0]).translate([-sx / 2, -sy / 2, 0.0])
    parts = partition(slab, cell, check_reach=False)
    pts = bed_points(cell, n, (0.0, cell.bed.max_height))
    inv = np.linalg.inv(cell.bed.pose)
    local = (pts @ inv[:3, :3].T + inv[:3, 3]) * 1000.0
    owner = np.full(len(pts), -1)
    for i, part in enumerate(parts):
        inside = np.all([local @ np.asarray(nrm) - off >= -1e-6 for nrm, off in part.planes], axis=0)
        owner[(owner < 0) & inside] = i
    return owner, pts


def _write(path, text):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)
