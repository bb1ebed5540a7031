"""ambots.parallel: work in forked processes, results and errors back in
order, nothing left behind; and a job planned with workers equals the job
planned in one process."""
import glob
import os
import signal
import tempfile

import numpy as np
import pytest
import trimesh

from ambots import parallel
from ambots.config import default_cell_path, load_cell
from ambots.errors import MeshError
from ambots.parallel import Forked, WorkerError, fork_map


@pytest.fixture
def jobs(monkeypatch):
    def set_jobs(n):
        monkeypatch.setenv(parallel.JOBS_ENV, str(n))
    return set_jobs


def _leftovers():
    return set(glob.glob(os.path.join(tempfile.gettempdir(), "ambots-worker-*")))


def test_results_in_order_from_other_processes(jobs):
    jobs(2)
    before = _leftovers()
    out = fork_map(lambda x: (x * x, os.getpid()), range(7))
    assert [v for v, _ in out] == [x * x for x in range(7)]
    pids = {p for _, p in out}
    assert os.getpid() in pids and len(pids) > 1      # this process took some, children the others
    assert _leftovers() == before                     # every result file removed


def test_one_job_runs_everything_here(jobs):
    jobs(1)
    assert {p for p in fork_map(lambda x: os.getpid(), range(5))} == {os.getpid()}
    f = Forked(lambda: os.getpid())
    assert f.pid is None and f.result() == os.getpid()


def test_a_large_result_comes_back_whole(jobs):
    jobs(2)
    a = np.random.default_rng(1).random(2_000_000)    # 16 MB, far more than a pipe holds
    out = fork_map(lambda k: a * k, [1.0, 2.0, 3.0])
    for k, v in zip([1.0, 2.0, 3.0], out):
        np.testing.assert_array_equal(v, a * k)


def test_a_workers_error_is_raised_here_in_item_order(jobs):
    jobs(2)

    def fn(x):
        if x in (1, 3):
            raise MeshError("model %d: broken" % x)
        return x
    with pytest.raises(MeshError, match="model 1: broken"):
        fork_map(fn, range(4))


def test_an_error_that_cannot_be_pickled_keeps_its_type_and_message(jobs):
    jobs(2)

    class Local(Exception):                           # a local class cannot be pickled
        pass

    def fn(x):
        if x == 0:
            raise Local("no reach for line 12")
        return x
    with pytest.raises(WorkerError, match="Local: no reach for line 12"):
        fork_map(fn, range(2))


@pytest.mark.parametrize("how, said", [(lambda: os._exit(3), "exit code 3"),
                                       (lambda: os.kill(os.getpid(), signal.SIGKILL), "signal 9")])
def test_a_worker_that_dies_is_reported(jobs, how, said):
    jobs(2)
    f = Forked(how)
    assert f.pid is not None
    with pytest.raises(WorkerError, match="died .*%s" % said):
        f.result()


def test_a_worker_starts_no_workers_of_its_own(jobs):
    jobs(2)
    f = Forked(lambda: (os.getpid(), {p for p in fork_map(lambda x: os.getpid(), range(4))}))
    pid, inner = f.result()
    assert pid != os.getpid() and inner == {pid}


def test_a_working_child_counts_against_the_workers(jobs):
    """With 2 CPUs and one child still working, a map runs here (no third
    process); once that child has ended, a map forks again."""
    import time
    jobs(2)
    r, w = os.pipe()
    f = Forked(lambda: os.read(r, 1))                 # works until told
    try:
        assert {p for p in fork_map(lambda x: os.getpid(), range(4))} == {os.getpid()}
        # a map told not to share (the job's last timing: its background worker is about to end) forks
        assert len({p for p in fork_map(lambda x: (time.sleep(0.05), os.getpid())[1], range(4), share=False)}) == 2
    finally:
        os.write(w, b"x")
    assert f.result() == b"x"
    assert len({p for p in fork_map(lambda x: (time.sleep(0.05), os.getpid())[1], range(4))}) == 2
    os.close(r)
    os.close(w)


def test_a_worker_does_not_count_its_parents_children(jobs):
    """A worker forked while another child works sees no children of its
    own (it would wait for a process that is not its child)."""
    jobs(3)
    r, w = os.pipe()
    first = Forked(lambda: os.read(r, 1))
    try:
        second = Forked(lambda: (len(parallel._LIVE), fork_map(lambda x: x + 1, range(3))))
        assert second.result() == (0, [1, 2, 3])
    finally:
        os.write(w, b"x")
    assert first.result() == b"x"
    os.close(r)
    os.close(w)


def test_cancel_stops_the_worker(jobs):
    jobs(2)
    before = _leftovers()
    f = Forked(lambda: __import__("time").sleep(60))
    pid = f.pid
    f.cancel()
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)                   # gone and reaped
    assert _leftovers() == before


def test_a_bad_jobs_setting_is_named(jobs):
    jobs("two")
    with pytest.raises(WorkerError, match="AMBOTS_JOBS='two'"):
        parallel.workers()


def test_a_job_planned_with_workers_is_the_job_planned_in_one_process(jobs, tmp_path):
    """The planner's choice (each arm alone beside the arms together, each
    plan's arms timed side by side) gives the same plans as one process:
    the same candidates and chosen programs, the chosen arm's part, and the
    cell's own arm objects."""
    from ambots.job import run_job
    cell = load_cell(default_cell_path())
    path = str(tmp_path / "cube.stl")
    trimesh.creation.box((30.0, 30.0, 4.0)).export(path)
    out = {}
    for n in (1, 2):
        jobs(n)
        out[n] = run_job(path, cell)
    one, two = out[1], out[2]
    assert [c.arms for c in one.candidates] == [c.arms for c in two.candidates]
    for a, b in zip(one.candidates, two.candidates):
        assert b.makespan_s == pytest.approx(a.makespan_s, rel=0.005)   # OMPL's samples may differ
    assert {n: p.text for n, p in one.programs.items()} == {n: p.text for n, p in two.programs.items()}
    assert [p.arm.name for p in two.parts] == two.chosen.arms
    assert abs(two.parts[0].volume - one.parts[0].volume) < 1e-6 * one.parts[0].volume
    assert all(p.arm is cell.arm(n) for n, p in two.programs.items())
    # the chosen arm's G-code of the whole model: the worker's text, sent back as plain text
    # (without the writer's reading); in one process the text as written, with it
    assert len(two.chosen.arms) == 1 and two.sliced == one.sliced
    name = two.chosen.arms[0]
    assert type(two.sliced[name]) is str and one.sliced[name].layers is not None


def test_the_urdfs_made_aside_are_those_xacro_makes_here(jobs, monkeypatch):
    """:func:`ambots.model.prefetch_urdfs`: xacro runs in a worker for the
    profiles not kept yet, and what comes back is kept: the texts xacro
    gives in this process, and xacro is not run again for them."""
    import xacro

    from ambots import model
    jobs(2)
    profiles = [a.profile for a in load_cell(default_cell_path()).arms]
    monkeypatch.setattr(model, "_URDF", {})
    want = {model._urdf_key(p): model.arm_urdf(p) for p in profiles}      # here
    monkeypatch.setattr(model, "_URDF", {})
    keep, _ = model.prefetch_urdfs(profiles)
    keep()
    assert model._URDF == want and len(want) == 2            # the Kinova's and the UR10's
    calls = []
    monkeypatch.setattr(xacro, "process_file", lambda *a, **k: calls.append(a))
    assert [model.arm_urdf(p) for p in profiles] == [want[model._urdf_key(p)] for p in profiles]
    assert not calls
