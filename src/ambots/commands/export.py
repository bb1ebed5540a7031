"""``python -m ambots export DIR --format trajectory|urscript``: a planned job
for real controllers (see :mod:`ambots.export`)."""


def register(sub):
    p = sub.add_parser("export", help="write a planned job as joint trajectories (CSV) or URScript programs",
                       description="Execute the programs of a `plan` output folder again with the firmware's "
                                   "motion pipeline and write, per arm, the joint trajectory timed by the firmware's one timing "
                                   "law "
                                   "(--format trajectory: <arm>.trajectory.csv + .yaml header) or a URScript "
                                   "program (--format urscript, Universal Robots arms only: <arm>.script).")
    p.add_argument("dir", help="output folder of `python -m ambots plan` (<arm>.gcode, job.json, report.json)")
    p.add_argument("--format", required=True, metavar="FORMAT", help="trajectory or urscript")
    p.add_argument("--arms", help="comma-separated subset of the job's arms (default: all)")
    p.add_argument("--cell", help="cell YAML the job was planned for (default: the package's cell job.json names)")
    p.add_argument("--out", help="folder for the exported files (default: DIR)")
    p.add_argument("--extruder-output", default="tool:0", metavar="tool:N|standard:N",
                   help="URScript: the digital output that switches the extruder (default tool:0)")
    p.add_argument("--tool-acceleration", type=float, default=1.2, metavar="M_S2",
                   help="URScript: tool acceleration of the movel moves, m/s^2 (default 1.2)")
    p.add_argument("--force", action="store_true",
                   help="export even if report.json is missing or reports collisions or an unfinished run")
    p.set_defaults(func=run)


def run(args):
    import sys

    from ambots.export import export_plan

    s = export_plan(args.dir, args.format, arms=args.arms, cell=args.cell, out=args.out,
                    force=args.force, extruder_output=args.extruder_output,
                    tool_acceleration=args.tool_acceleration)
    for w in s["warnings"]:
        print("ambots: warning: %s" % w, file=sys.stderr)
    print("%s -> %s: %s, cell %s, %s timing, makespan %.1f s (simulated)" % (
        s["plan"], s["out"], s["format"], s["cell"], s["timing"], s["makespan_s"]))
    for name, a in s["arms"].items():
        if s["format"] == "trajectory":
            c = a["checks"]
            w = c["acceleration_worst"]
            acc = "within limits" if c["acceleration_ok"] else (
                "over the limit at %d waypoints (worst %s %.3g rad/s^2 at %.3f s, line %d)"
                % (c["acceleration_rows_over_limit"], w["joint"], w["acceleration"], w["time_s"], w["line"]))
            print("  %-8s %d samples, %.1f s; joint speeds within limits; accelerations %s"
                  % (name, a["samples"], a["duration_s"], acc))
        else:
            print("  %-8s %d movel, %d movej, %d sleep (%.1f s), %d lines"
                  % (name, a["movel"], a["movej"], a["sleeps"], a["sleep_s"], a["lines"]))
        for f in a["files"]:
            print("    %s" % f)
    return 0
