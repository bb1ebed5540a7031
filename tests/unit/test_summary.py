"""`python -m ambots summary DIR`: the lines `make demo` and `make print` end
with, and the exit status that tells a script whether the print succeeded."""
import json
import subprocess
import sys


def _run(tmp_path, report=None, job=None, png=True, *flags):
    if report is not None:
        (tmp_path / "report.json").write_text(json.dumps(report))
    if job is not None:
        (tmp_path / "job.json").write_text(json.dumps(job))
    if png:
        (tmp_path / "capture.png").write_bytes(b"\x89PNG not really")
    r = subprocess.run([sys.executable, "-m", "ambots", "summary", *flags, str(tmp_path)],
                       capture_output=True, text=True)
    return r.returncode, r.stdout


def _report(finished=True, contacts=0):
    return {"model": "m.stl", "cell": "kinova_ur10", "mode": "concurrent", "finished": finished,
            "arms": {"kinova": {"state": "DONE" if finished else "ERROR", "error": None if finished else "IK"},
                     "ur10": {"state": "DONE"}},
            "makespan_s": 4000.0, "wall_time_s": 30.0, "min_clearance_mm": 12.34,
            "collisions": {"arm_arm": contacts, "arm_bed": 0, "arm_part": 0}}


def test_a_finished_print_says_makespan_speed_up_and_where_the_files_are(tmp_path):
    plan = {"arms": ["kinova", "ur10"], "how": "concurrent", "forced": False,
            "candidates": [{"arms": ["kinova", "ur10"], "how": "concurrent", "makespan_s": 4010.0},
                           {"arms": ["kinova"], "how": "alone", "makespan_s": 7500.0},
                           {"arms": ["ur10"], "how": "alone", "makespan_s": 7000.0}]}
    code, out = _run(tmp_path, _report(), {"plan": plan}, True, "--capture")
    assert code == 0, out
    assert out.startswith("FINISHED: m.stl on cell kinova_ur10, 2 arms, concurrent mode")
    assert "4,000 s simulated (1 h 06 min)" in out
    assert ("plan: 2 arms concurrent (kinova, ur10): 4,010 s; best single arm (ur10): 7,000 s; speed-up %.2fx"
            % (7000 / 4010)) in out
    assert "also considered: kinova alone 7,500 s; ur10 alone 7,000 s" in out
    assert "contacts      0" in out and "closest approach of two arms 12.3 mm" in out
    assert str(tmp_path / "capture.png") in out and str(tmp_path / "report.json") in out
    assert "close-up" not in out
    assert len(out.splitlines()) <= 8          # short
    (tmp_path / "capture_closeup.png").write_bytes(b"\x89PNG not really")
    code, out = _run(tmp_path, None, None, True, "--capture")
    assert "picture       %s, close-up %s" % (tmp_path / "capture.png", tmp_path / "capture_closeup.png") in out
    assert len(out.splitlines()) <= 8


def test_one_arm_chosen_is_said_so(tmp_path):
    plan = {"arms": ["ur10"], "how": "alone", "forced": False,
            "candidates": [{"arms": ["ur10"], "how": "alone", "makespan_s": 552.0},
                           {"arms": ["kinova", "ur10"], "how": "concurrent", "makespan_s": 648.0}]}
    rep = _report()
    rep["arms"]["kinova"]["state"] = "IDLE"          # parked, no program
    code, out = _run(tmp_path, rep, {"plan": plan}, True, "--capture")
    assert code == 0, out
    assert out.startswith("FINISHED: m.stl on cell kinova_ur10, ur10 alone")
    assert "plan: ur10 alone: 552 s" in out and "also considered: 2 arms concurrent (kinova, ur10) 648 s" in out


def test_an_unfinished_print_fails_and_names_the_arm(tmp_path):
    code, out = _run(tmp_path, _report(finished=False), {}, True, "--capture")
    assert code == 1 and out.startswith("NOT FINISHED") and "kinova: IK" in out


def test_contacts_fail_the_run(tmp_path):
    code, out = _run(tmp_path, _report(contacts=3))
    assert code == 1 and out.startswith("FINISHED WITH CONTACTS") and "arm-arm 3" in out


def test_unchecked_motion_fails_the_run(tmp_path):
    rep = _report()
    rep["collisions"] = None
    code, out = _run(tmp_path, rep)
    assert code == 1 and "NOT CHECKED" in out


def test_a_missing_capture_fails_a_live_run_only(tmp_path):
    code, out = _run(tmp_path, _report(), {}, False, "--capture")
    assert code == 1 and "picture       MISSING" in out
    code, out = _run(tmp_path, None, None, False)            # offline (`plan`): no picture expected
    assert code == 0, out


def test_no_report_at_all_fails_with_a_reason(tmp_path):
    code, out = _run(tmp_path, None, None, False, "--capture")
    assert code == 1 and "no report.json" in out


def test_a_seam_plan_not_kept_says_why_in_the_brief_lines_too():
    """A stepped seam faster by less than the share the estimate can tell
    apart: its note is on the run summaries' line, not only in ``slice``'s."""
    from ambots.job import plan_lines
    note = "within 0.2 % of the plan with the seam straight, which is kept"
    plan = {"arms": ["kinova", "ur10"], "how": "concurrent", "forced": False, "seam_steps_mm": None,
            "candidates": [{"arms": ["kinova", "ur10"], "how": "concurrent", "makespan_s": 5098.4},
                           {"arms": ["kinova", "ur10"], "how": "concurrent", "makespan_s": 5097.3,
                            "seam_steps_mm": [-1.1, 0.8], "note": note},
                           {"arms": ["ur10"], "how": "alone", "makespan_s": 9598.1}]}
    brief = plan_lines(plan, brief=True)
    assert brief[1] == ("  also considered: 2 arms concurrent, seam stepped per layer (-1.1 to +0.8 mm) (kinova, ur10) "
                        "5,097 s (%s); ur10 alone 9,598 s" % note)
    assert "5,097 s (%s)" % note in plan_lines(plan)[1]
