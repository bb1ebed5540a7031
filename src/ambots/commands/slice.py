"""``python -m ambots slice``: model -> parts -> G-code -> per-arm programs."""


def register(sub):
    p = sub.add_parser("slice", help="split a model among the arms, slice it, write per-arm programs",
                       description="Read a model (STL, OBJ, PLY, 3MF; mm), centre it on the bed, split it "
                                   "among the cell's arms, slice every part and coordinate the per-arm "
                                   "programs. Writes DIR/<arm>.gcode, DIR/<arm>.stl, DIR/job.json and, when the model was repaired, DIR/model_repaired.stl.")
    add_job_arguments(p, "out/slice")
    p.set_defaults(func=run)


def add_job_arguments(p, out):
    """The options of a job (shared by ``slice`` and ``plan``)."""
    p.add_argument("model", help="model file, millimetres")
    p.add_argument("--cell", help="cell YAML (default: config/cells/kinova_ur10.yaml)")
    p.add_argument("--arms", help="comma-separated arms to print with, e.g. ur10 (default: the planner "
                                  "chooses the fastest of all the cell's arms together and each arm alone)")
    p.add_argument("--slicer", choices=("builtin", "prusa"), default="builtin")
    p.add_argument("--mode", choices=("concurrent", "sequential"), default="concurrent")
    p.add_argument("--seam", choices=("straight", "interlock", "overlap"), default="straight",
                   help="between two arms' parts: straight (they meet at a plane) or interlock (the boundary "
                        "alternates layer by layer either side of the plane; overlap is the same)")
    p.add_argument("--scale", type=float, default=1.0, help="scale factor applied to the model")
    p.add_argument("--support", choices=("on", "off"), default="on",
                   help="support under overhangs steeper than 45 deg from vertical (default: on; a model "
                        "without overhangs gets none either way)")
    p.add_argument("--out", default=out, help="output folder (default: %s)" % out)


def job_settings(args):
    """The :class:`~ambots.slicer.SliceSettings` of the job options (``--support``)."""
    from ambots.slicer import SliceSettings
    return SliceSettings(support=getattr(args, "support", "on") == "on")


def run(args):
    from ambots.config import default_cell_path, load_cell
    from ambots.job import run_job, write_job

    cell = load_cell(args.cell or default_cell_path())
    arms = [cell.arm(n.strip()) for n in args.arms.split(",")] if args.arms else None
    job = run_job(args.model, cell, arms, args.slicer, args.mode, args.seam, args.scale,
                  settings=job_settings(args))
    summary = write_job(job, args.out)
    print("%s -> %s: %s, %s slicer, %s mode, model %.0f mm3" % (
        args.model, args.out, cell.name, args.slicer, args.mode, summary["model_volume_mm3"]))
    from ambots.job import overhang_lines, plan_lines, unsupported_line
    from ambots.repair import repair_lines
    for line in repair_lines(summary.get("repair")):
        print("  " + line)
    for line in plan_lines(summary["plan"]):
        print("  " + line)
    print("  " + unsupported_line(summary["overhang"]))
    for line in overhang_lines(summary["overhang"]):
        print("  " + line)
    from ambots.job import arm_time_columns
    print("  %-8s %4s %10s %7s %7s %11s %11s %8s %8s" % ("arm", "id", "part mm3", "layers", "moves",
                                                       "extrude mm", "filament mm", "busy s", "done s"))
    for name, a in summary["arms"].items():
        print("  %-8s R%-3d %10.0f %7d %7d %11.1f %11.1f %s" % (
            name, a["id"], a["part_volume_mm3"], a["layers"], a["moves"], a["extrude_path_mm"],
            a["extruded_filament_mm"], arm_time_columns(a)))
        if a["stripped_lines"]:
            print("    stripped %d A-series line(s) from the slicer output: %s" % (
                len(a["stripped_lines"]), ", ".join(str(l["line"]) for l in a["stripped_lines"])))
    return 0
