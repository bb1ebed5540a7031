"""`make faults`: the fault figures of the README, measured on the running
system (real roscore, hub, firmware nodes, front end; see tests/ros/faults.py):
a clean print of a small two-arm job, the same job with 20 % drop + 10 %
duplication + reordering on every hub topic, the same with the Kinova's
firmware killed (SIGKILL) mid-print, the same with the hub and the front
end killed instead (hub respawned, a new front end --follow), with the UR10 30 % slower than
planned, and the demo model clean and under the same faults; plus the hostile-input suite (tests/unit/test_hostile.py).
Segments lost / duplicated: per arm and G-code line, filament in the deposit
journal against the program (each extrusion must be printed exactly once)."""
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "ros"))

FAULTS = "drop=0.2 dup=0.1 reorder=0.3 reorder_window=0.05 delay=0.002 seed=%d"


def main():
    from faults import coverage, run_print, small_model
    tmp = tempfile.mkdtemp(prefix="ambots-faults-")
    model = small_model(os.path.join(tmp, "block.stl"))
    from ambots import data_path
    from ambots.job import DEMO_MODEL
    demo = data_path(DEMO_MODEL)
    runs = [("clean", {}), ("faults seed 7", {"faults": FAULTS % 7}),
            ("faults seed 8 + kill -9", {"faults": FAULTS % 8, "kill_after": 0.8}),
            ("faults seed 5 + hub and front end kill -9", {"faults": FAULTS % 5, "kill_hub_after": 0.3,
                                                           "replace_front_end_after": 0.8}),
            ("ur10 30 % slower", {"slowdown": "ur10=1.3"}),
            ("demo model, clean", {"model": demo}),
            ("demo model, faults seed 7", {"model": demo, "faults": FAULTS % 7})]
    rows = []
    for i, (label, kw) in enumerate(runs):
        kw = dict(kw)
        run = run_print(os.path.join(tmp, "run%d" % i), 11650 + i, kw.pop("model", model), **kw)
        rep = run["report"] or {}
        hub = (rep.get("hub_progress") or {})
        f = hub.get("faults", {})
        fin, fout = f.get("in", {}), f.get("out", {})
        lost = dup = 0
        for arm, journal in run["journals"].items():
            missing, extra, diff = coverage(journal, os.path.join(run["tmp"], "job", arm + ".gcode"))
            lost += len(missing)
            dup += len(extra) + (diff > 1e-5)
        rows.append((label, run["front_end_rc"] == 0 and rep.get("finished"),
                     fin.get("messages", 0) + fout.get("messages", 0) if f else None,
                     fin.get("dropped", 0) + fout.get("dropped", 0),
                     fin.get("duplicated", 0) + fout.get("duplicated", 0),
                     fin.get("reordered", 0) + fout.get("reordered", 0),
                     hub.get("hub", {}).get("retries"), run["kills"], lost, dup,
                     sum((rep.get("collisions") or {}).values()) if rep.get("collisions") else None))
        print("  %-26s done" % label, flush=True)
    hostile = _hostile_cases()
    print("| run | finished | messages through the hub | dropped | duplicated | reordered | hub retries "
          "| kills survived | segments lost | segments duplicated | collisions |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print("| %s |" % " | ".join("-" if v is None else str(v) for v in r))
    print("hostile inputs tried: %s (tests/unit/test_hostile.py, each with its error text)" % hostile)


def _hostile_cases():
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", os.path.join(HERE, "..", "unit", "test_hostile.py")],
                       capture_output=True, text=True)
    last = (r.stdout.strip().splitlines() or ["?"])[-1]
    return last


if __name__ == "__main__":
    main()
