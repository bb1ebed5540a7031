"""The firmware's durable state (ambots.checkpoint): the bead and trace
journals are cut back to what the checkpoint covers after a crash, a new
run empties the deposit journal (a clean start both), and a checkpoint written before the trace journal
existed still resumes."""
import numpy as np

from ambots.checkpoint import RECORD, StateStore, write_json

DOF = 6


def _knots(t0, n, rng):
    """n Hermite knots (t, q (6), v (6)) from time t0."""
    return np.column_stack([t0 + np.arange(n) * 0.5, rng.normal(size=(n, DOF)), rng.normal(size=(n, DOF))])


def _beads(store, n, t0, rng):
    p = rng.normal(size=(n, 6))
    store.append(p[:, :3], p[:, 3:], np.full(n, 0.5), np.arange(n), np.zeros(n), t0 + np.arange(n))
    return p


def test_a_crash_cuts_both_journals_back_to_the_checkpoint(tmp_path):
    rng = np.random.default_rng(1)
    store = StateStore(str(tmp_path), "kinova", dof=DOF)
    store.start_clean()
    k1 = _knots(0.0, 40, rng)
    store.append_trace(k1)
    p1 = _beads(store, 25, 0.0, rng)
    store.save({"runner": "a"})
    store.append_trace(_knots(20.0, 7, rng))        # a step after the checkpoint, then kill -9
    _beads(store, 3, 25.0, rng)
    store._flush()

    again = StateStore(str(tmp_path), "kinova", dof=DOF)       # the respawned node
    cp = again.load()
    assert (cp["records"], cp["trace_records"]) == (25, 40)
    assert len(again.read_trace()) == 47                        # on disk: the step that was not checkpointed
    again.reopen(cp["records"], cp["trace_records"])
    np.testing.assert_array_equal(again.read_trace(), k1)
    beads = again.read_journal()
    assert beads.shape == (25, RECORD)
    np.testing.assert_array_equal(beads[:, 0:6], p1)
    k2 = _knots(20.0, 5, rng)                                   # the resumed run goes on
    again.append_trace(k2)
    np.testing.assert_array_equal(again.read_trace(), np.vstack([k1, k2]))
    assert again.trace_records == 45


def test_a_new_run_empties_the_deposit_journal_and_a_clean_start_both(tmp_path):
    """A new run (A5, A1 again) starts a new deposit; the executed motion
    goes on (an A7 before the A1 moved the arm too)."""
    rng = np.random.default_rng(2)
    store = StateStore(str(tmp_path), "ur10", dof=DOF)
    store.start_clean()
    k = _knots(0.0, 10, rng)
    store.append_trace(k)
    _beads(store, 4, 0.0, rng)
    store.new_journal()
    assert store.read_journal().shape == (0, RECORD)
    np.testing.assert_array_equal(store.read_trace(), k)
    store.save({})
    assert (store.load()["records"], store.load()["trace_records"]) == (0, 10)
    store.start_clean()
    assert store.read_trace().shape == (0, 1 + 2 * DOF) and store.read_journal().shape == (0, RECORD)


def test_a_checkpoint_from_before_the_trace_journal_resumes(tmp_path):
    """An older checkpoint has no trace_records: the trace journal resumes
    empty (nothing of it was written) and the beads are kept."""
    rng = np.random.default_rng(3)
    old = StateStore(str(tmp_path), "kinova")
    old.new_journal()
    _beads(old, 6, 0.0, rng)
    old.save({})
    cp = old.load()
    del cp["trace_records"]                                 # as the firmware wrote it before
    write_json(old.checkpoint_file, cp)
    store = StateStore(str(tmp_path), "kinova", dof=DOF)
    cp = store.load()
    store.reopen(cp["records"], cp.get("trace_records", 0))
    assert len(store.read_journal()) == 6 and len(store.read_trace()) == 0
    store.append_trace(_knots(3.0, 2, rng))
    assert store.trace_records == 2
