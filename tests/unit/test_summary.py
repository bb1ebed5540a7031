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
    code, out = _run(tmp_path, _report(), {"one_arm_estimate_s": 7000.0}, True, "--capture")
    assert code == 0, out
    assert out.startswith("FINISHED: m.stl on cell kinova_ur10, 2 arms, concurrent mode")
    assert "4,000 s simulated (1 h 06 min)" in out
    assert "one arm alone 7,000 s" in out and "speed-up %.2fx" % (7000 / 4000) in out
    assert "contacts      0" in out and "closest approach of two arms 12.3 mm" in out
    assert str(tmp_path / "capture.png") in out and str(tmp_path / "report.json") in out
    assert len(out.splitlines()) <= 8          # short


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
