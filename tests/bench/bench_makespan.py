"""Cooperative printing, measured with `python -m ambots plan` (the firmware's
motion pipeline on a simulated clock): makespan of the demo model printed by
both arms concurrently divided by the makespan of one arm printing it alone
(goal <= 0.55), and the simulation speed (simulated seconds per wall second
of the offline run, planning included; goal >= 200).  Both runs side by side
in one process.  Then the timing law's cost: the same two-arm job timed by
the firmware's one timing law (joint speed and acceleration limits, nozzle
at most at the feedrate) and by the law it replaced (the feedrate alone,
stretched only for joint speeds, no acceleration limit -- kept here only as
the baseline: the planner's waypoints without ``SplineTiming``)."""
from ambots import data_path
from ambots.commands.plan import plan_job
from ambots.config import default_cell_path, load_cell
from ambots.job import DEMO_MODEL


def main():
    cell = load_cell(default_cell_path())
    model = data_path(*DEMO_MODEL.split("/"))
    runs = {}
    for label, arms in (("kinova alone", [cell.arm("kinova")]), ("ur10 alone", [cell.arm("ur10")]),
                        ("both, concurrent", list(cell.arms))):
        rep = plan_job(model, cell, arms)
        runs[label] = rep
        sim_s = sum(a["print_time_s"] + a["idle_time_s"] for a in rep["arms"].values())
        print("makespan %-17s %7.0f s simulated, collisions %s, min clearance %s mm; sim wall %.1f s "
              "-> %.0f simulated arm-seconds per wall second"
              % (label, rep["makespan_s"], sum(rep["collisions"].values()), rep["min_clearance_mm"],
                 rep["sim_wall_time_s"], sim_s / rep["sim_wall_time_s"]), flush=True)
    alone = min(runs["kinova alone"]["makespan_s"], runs["ur10 alone"]["makespan_s"])
    both = runs["both, concurrent"]["makespan_s"]
    print("makespan 2 arms / best single arm = %.0f / %.0f = %.3f (goal <= 0.55)" % (both, alone, both / alone))
    timing_law(model, cell, runs["both, concurrent"])


def _feedrate_only(block, scale=1.0):
    """The former timing: the planner's own times, untouched."""
    block.motion = None
    return block


def timing_law(model, cell, rep):
    from ambots.job import run_job
    from ambots.sim import check_motion, simulate
    job = run_job(model, cell, list(cell.arms))
    old = simulate(job.programs, cell, planner_kw={"timing": _feedrate_only})
    motion = check_motion(old, cell)
    print("timing law: demo makespan, one timing law %.0f s vs feedrate only (before) %.0f s = %+.1f %%; "
          "collisions %s vs %s" % (rep["makespan_s"], old.makespan_s, 100.0 * (rep["makespan_s"] / old.makespan_s - 1),
                                   sum(rep["collisions"].values()), sum(motion["collisions"].values())), flush=True)


if __name__ == "__main__":
    main()
