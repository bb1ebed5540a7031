"""Runs every rostest suite in tests/ros (*.test) with a real roscore and real
nodes, so that `make test` (pytest) covers them and ends with pytest's summary.
Needs the catkin workspace sourced (the Makefile does it)."""
import glob
import os
import subprocess

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
SUITES = sorted(os.path.basename(p) for p in glob.glob(os.path.join(HERE, "*.test")))


def test_there_are_rostest_suites():
    assert "cell.test" in SUITES


@pytest.mark.parametrize("suite", SUITES)
def test_rostest(suite, tmp_path):
    env = dict(os.environ, ROS_HOME=str(tmp_path / "ros_home"))
    # output to a file, not a pipe: a stray grandchild holding a pipe open must not hang the test
    log = tmp_path / "rostest.log"
    with open(log, "w") as f:
        r = subprocess.run(["rostest", "ambots", suite], stdout=f, stderr=subprocess.STDOUT, text=True,
                           timeout=600, env=env)
    out = log.read_text()
    assert r.returncode == 0 and "RESULT: SUCCESS" in out, out[-6000:]
