"""``python -m ambots summary DIR``: a finished run in a few lines for people.

Reads what a run wrote into DIR (``report.json``, ``job.json``,
``capture.png``, and ``capture_closeup.png`` if there) -- `make demo`,
`make print` and `python -m ambots plan` write them -- and exits 0 only when the print finished with no contact and,
for a live run, the capture is there."""
import json
import os


def register(sub):
    p = sub.add_parser("summary", help="say in a few lines how a run went (finished, makespan, speed-up)",
                       description="Summarise the run in DIR (report.json, job.json, capture.png): finished "
                                   "or not, makespan, speed-up against one arm alone, closest approach, "
                                   "where the files are.  Exit status 1 when the print did not finish, an "
                                   "arm touched something, or (--capture) the picture is missing.")
    p.add_argument("dir", help="the run's output folder (e.g. out/demo)")
    p.add_argument("--capture", action="store_true",
                   help="the run is live (make demo / make print): capture.png must be there")
    p.set_defaults(func=run)


def _load(path):
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        return None
    except ValueError as exc:
        from ambots.errors import AmbotsError
        raise AmbotsError("%s: not valid JSON: %s" % (path, exc)) from None


def _duration(s):
    s = int(round(s))
    return "%d h %02d min" % (s // 3600, s % 3600 // 60) if s >= 3600 else "%d min %02d s" % (s // 60, s % 60)


def _shown(path):
    """A file name as a person wants to read it: relative to the current
    folder when inside it (the demo model is reached through the catkin
    workspace's link to the package)."""
    if not path:
        return path
    real = os.path.realpath(path)
    rel = os.path.relpath(real)
    return real if rel.startswith("..") else rel


def summary_lines(out_dir, capture=False):
    """(lines, ok) for the run in ``out_dir``."""
    rep = _load(os.path.join(out_dir, "report.json"))
    job = _load(os.path.join(out_dir, "job.json")) or {}
    png = os.path.join(out_dir, "capture.png")
    if rep is None:
        return ["NOT FINISHED: no report.json in %s (the run stopped before its end; see the log above)"
                % out_dir], False
    finished = bool(rep.get("finished"))
    contacts = rep.get("collisions")
    checked = isinstance(contacts, dict)
    n_contacts = sum(int(v) for v in contacts.values()) if checked else 0
    has_png = os.path.isfile(png) and os.path.getsize(png) > 0
    arms = rep.get("arms") or {}
    head = "FINISHED" if finished else "NOT FINISHED"
    if finished and n_contacts:
        head = "FINISHED WITH CONTACTS"
    plan = job.get("plan") or rep.get("plan") or {}
    working = plan.get("arms") or list(arms)            # the arms with work (the planner may choose one)
    how = ("%s alone" % working[0] if len(working) == 1 and len(arms) > 1
           else "%d arm%s, %s mode" % (len(working), "" if len(working) == 1 else "s", rep.get("mode")))
    lines = ["%s: %s on cell %s, %s" % (head, _shown(rep.get("model")), rep.get("cell"), how)]
    if not finished:
        states = ", ".join("%s %s" % (n, a.get("state")) for n, a in arms.items())
        lines.append("  arms: %s%s" % (states, "; " + str(rep.get("reason")) if rep.get("reason") else ""))
        for n, a in arms.items():
            if a.get("error"):
                lines.append("  %s: %s" % (n, a["error"]))
    makespan = rep.get("makespan_s")
    if makespan:
        wall = rep.get("wall_time_s")
        lines.append("  makespan      %s s simulated (%s)%s" % (
            format(round(makespan), ","), _duration(makespan), ", %.0f s wall" % wall if wall else ""))
        from ambots.job import plan_lines
        lines += ["  " + line for line in plan_lines(plan, brief=True)]
        if not plan and job.get("one_arm_estimate_s") and len(arms) > 1:     # a job.json of before
            alone = job["one_arm_estimate_s"]
            lines.append("  one arm alone %s s (estimate); speed-up %.2fx" % (format(round(alone), ","),
                                                                         alone / makespan))
    clearance = rep.get("min_clearance_mm")
    if checked:
        lines.append("  contacts      %d (%s)%s" % (
            n_contacts, ", ".join("%s %s" % (k.replace("_", "-"), v) for k, v in contacts.items()),
            "; closest approach of two arms %.1f mm" % clearance if clearance is not None else ""))
    else:
        lines.append("  contacts      NOT CHECKED (no executed motion was received)")
    shares = rep.get("seam_bonded_share") or {}
    if shares:
        lines.append("  seam          %s: bonded share of the seam face %s" % (
            rep.get("seam"), ", ".join("%s %.3f" % (k, v["bonded_share"]) for k, v in shares.items())))
    if capture:
        closeup = os.path.join(out_dir, "capture_closeup.png")
        lines.append("  picture       %s%s" % (png if has_png else "MISSING (%s)" % png,
                                             ", close-up %s" % closeup if os.path.isfile(closeup) else ""))
    lines.append("  report        %s (also %s)" % (
        os.path.join(out_dir, "report.json"),
        ", ".join(f for f in ("deposit.ply", "job.json") if os.path.exists(os.path.join(out_dir, f)))
        + ", <arm>.gcode"))
    ok = finished and checked and n_contacts == 0 and (has_png or not capture)
    return lines, ok


def run(args):
    lines, ok = summary_lines(args.dir, capture=args.capture)
    print("\n".join(lines))
    return 0 if ok else 1
