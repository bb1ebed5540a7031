"""``python -m ambots plan``: the whole job offline (no ROS master): model ->
programs -> every arm's firmware on one simulated clock -> collisions,
deposit mesh and ``report.json``."""


def register(sub):
    p = sub.add_parser("plan", help="run a whole print offline at full speed and write report.json",
                       description="Slice and coordinate a model as `slice` does, then execute every arm's "
                                   "program with the firmware's motion pipeline (IK, interpolation, timing, "
                                   "barriers) on a simulated clock, check the executed motion for "
                                   "collisions and write DIR/report.json, DIR/deposit.ply and the per-arm "
                                   "programs.")
    from ambots.commands.slice import add_job_arguments
    add_job_arguments(p, "out/plan")
    p.add_argument("--slow", action="append", default=[], metavar="ARM=FACTOR",
                   help="make an arm run FACTOR times slower than planned (e.g. ur10=1.3), or each of its "
                        "moves by its own random factor in LO..HI (e.g. ur10=0.5:2.5; see --seed)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random factors of --slow ARM=LO:HI")
    p.set_defaults(func=run)


def plan_job(model, cell, arms=None, slicer="builtin", mode="concurrent", seam="straight", scale=1.0,
             slow=None, out=None, seed=0, settings=None):
    """Run the steps; returns the report dict (and writes files if ``out``).
    ``settings``: :class:`~ambots.slicer.SliceSettings` (None: the defaults)."""
    import json
    import os
    import time

    from ambots.job import run_job, write_job
    from ambots.sim import check_motion, report, simulate

    t0 = time.perf_counter()
    job = run_job(model, cell, arms, slicer, mode, seam, scale, settings=settings)
    t_job = time.perf_counter() - t0
    # the cell's arms without a program stand at home until parked (A7): simulated and checked too
    idle = [a for a in cell.arms if a.name not in job.programs]
    result = simulate(job.programs, cell, slow=slow, seed=seed, idle=idle)
    motion = check_motion(result, cell)
    rep = report(result, motion, job, wall_time_s=time.perf_counter() - t0)
    rep["slice_wall_time_s"] = round(t_job, 3)
    rep["sim_wall_time_s"] = round(result.wall_time_s, 3)
    deposit = deposit_of(result)
    rep["seam"] = job.seam
    rep["seam_bonded_share"], rep["seam_lap_order"] = seam_report(job, deposit, result)
    if out:
        write_job(job, out)
        rep["repair"] = job.repair()          # with the repaired mesh's file, now written
        if len(deposit):
            deposit.export(os.path.join(out, "deposit.ply"),
                           colours={n: r.arm.profile.colour for n, r in result.runners.items()}, scale=1000.0)
        rep["deposit_mesh"] = "deposit.ply"
        with open(os.path.join(out, "report.json"), "w") as f:
            json.dump(rep, f, indent=2)
    return rep


def seam_report(job, deposit, result=None, settings=None):
    """The job's seams in ``deposit``: ({"a/b": {"bonded_share", "samples"}}
    (:func:`ambots.seams.bonded_share`), {"a/b": {"layers", "early"}}: with
    the runners' ``result``, whether each arm laid its beads near the seam
    only after its neighbour's layer below there (:func:`ambots.seams.lap_order`,
    within the interlock's reach and a bead); ({}, {}) for a one-arm plan.
    The live capture measures its deposit the same way
    (:func:`ambots.seams.seam_figures` with ``job.json``'s ``seams``)."""
    import numpy as np

    from ambots.mesh import to_manifold
    from ambots.seams import beads_in_bed_mm, seam_figures
    setup = job.seam_setup(settings)
    if setup is None:
        return {}, {}
    by_arm = None
    if result is not None:
        by_arm = {}
        for name, r in result.runners.items():
            beads = [b for b in r.beads if len(b.e_mm)]
            if beads:
                by_arm[name] = tuple(np.concatenate([getattr(b, k) for b in beads]) for k in ("p0", "p1", "t"))
        by_arm = beads_in_bed_mm(by_arm, job.cell.bed.pose)
    return seam_figures(setup, to_manifold(job.mesh), deposit, job.cell.bed.pose, by_arm)


def deposit_of(result, layer_height_m=None):
    """The runners' beads as a :class:`~ambots.deposit.Deposit`
    (:func:`ambots.deposit.deposit_of_beads`, as the live capture builds it)."""
    import numpy as np
    from ambots.deposit import deposit_of_beads
    from ambots.slicer import SliceSettings
    h = layer_height_m or SliceSettings().layer_height_mm * 1e-3
    by_arm = {}
    for name, r in result.runners.items():
        beads = [b for b in r.beads if len(b.e_mm)]
        if beads:
            by_arm[name] = tuple(np.concatenate([getattr(b, k) for b in beads]) for k in ("p0", "p1", "e_mm"))
    return deposit_of_beads(by_arm, h)


def run(args):
    import numpy as np

    from ambots.config import default_cell_path, load_cell
    from ambots.errors import ConfigError

    cell = load_cell(args.cell or default_cell_path())
    arms = [cell.arm(n.strip()) for n in args.arms.split(",")] if args.arms else None
    slow = {}
    for item in args.slow:
        name, _, factor = item.partition("=")
        try:
            lo, colon, hi = factor.partition(":")
            value = (float(lo), float(hi)) if colon else float(factor)
            if not all(v > 0 for v in np.atleast_1d(value)):
                raise ValueError(factor)
            slow[cell.arm(name).name] = value
        except ValueError:
            raise ConfigError("--slow", item, "expected ARM=FACTOR or ARM=LO:HI with numbers > 0, "
                                              "e.g. ur10=1.3 or ur10=0.5:2.5") from None
    from ambots.commands.slice import job_settings
    rep = plan_job(args.model, cell, arms, args.slicer, args.mode, args.seam, args.scale, slow, args.out,
                   args.seed, job_settings(args))
    print("%s -> %s: %s, %s mode, makespan %.0f s (simulated), %s, wall %.1f s" % (
        args.model, args.out, rep["cell"], rep["mode"], rep["makespan_s"],
        "finished" if rep["finished"] else "NOT finished: " + rep["reason"], rep["wall_time_s"]))
    from ambots.job import overhang_lines, plan_lines, unsupported_line
    from ambots.repair import repair_lines
    for line in repair_lines(rep.get("repair")):
        print("  " + line)
    for line in plan_lines(rep.get("plan")):
        print("  " + line)
    if rep.get("overhang"):
        print("  " + unsupported_line(rep["overhang"]))
        for line in overhang_lines(rep["overhang"]):
            print("  " + line)
    for pair, v in rep["seam_bonded_share"].items():
        order = rep["seam_lap_order"].get(pair)
        print("  seam %s (%s): bonded share %.3f of %d points of the seam face%s" % (
            pair, rep["seam"], v["bonded_share"], v["samples"],
            "; %d of %d layers begun there before the neighbour's layer below was done" % (
                order["early"], order["layers"]) if order else ""))
    print("  collisions: %s; closest approach of two arms: %s mm" % (rep["collisions"], rep["min_clearance_mm"]))
    print("  %-8s %7s %11s %10s %9s %9s %5s %8s" % ("arm", "moves", "extrude mm", "travel mm", "print s",
                                                 "idle s", "ik!", "dev mm"))
    for name, a in rep["arms"].items():
        print("  %-8s %7d %11.0f %10.0f %9.0f %9.0f %5d %8.4f" % (
            name, a["moves"], a["extrude_mm"], a["travel_mm"], a["print_time_s"], a["idle_time_s"],
            a["ik_failures"], a["max_path_error_mm"]))
    for e in rep["errors"]:
        print("  error: arm R%d line %d: %s" % (e["arm"], e["line"], e["message"]))
    bad = sum(rep["collisions"].values()) or not rep["finished"]
    return 1 if bad else 0
