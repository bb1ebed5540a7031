"""A firmware's durable state, so that a node killed at any moment (``kill
-9``) resumes where it stopped: no bead missing, none laid twice, no
command executed twice.  ROS-free.

Files in the state directory, per arm:

* ``<arm>.chunk.json``: the loaded chunk (identity and G-code text),
  written once per A5;
* ``<arm>.beads``: the deposit journal, append-only records of
  :data:`RECORD` float64 (p0 xyz, p1 xyz in m, world frame; filament mm;
  G-code line; layer; simulated time s);
* ``<arm>.trace``: the executed motion's journal, append-only records of
  ``1 + 2 n`` float64 (simulated time s, n joint positions rad, n joint
  speeds rad/s: the Hermite knots the firmware publishes on ``~trace``),
  the node's whole ROS run (the deposit journal is one run of a chunk);
* ``<arm>.checkpoint.json``: the runner's :meth:`~ambots.runner.ArmRunner.checkpoint`,
  the receiver's and sender's snapshots, the number of records of each
  journal it covers (``records``, ``trace_records``) and the ROS run id.

Order of a step (the firmware's loop): journal the new beads and knots, then
write the checkpoint (atomically: temporary file + ``os.replace``), then
publish.  After a crash the journals are cut back to the records the
checkpoint covers, so beads of a step that was not checkpointed are laid
again by the resumed run, never twice.  What was published but never
delivered (a publisher's queue dies with its process) is in the journals:
the resumed firmware publishes the run's beads and knots again, so a
recorder of the executed motion never interpolates across a hole.
``fsync`` is optional (``durable=True``): a killed process loses nothing
the kernel has; a power cut needs it.
"""
import json
import os

import numpy as np

__all__ = ["StateStore", "RECORD", "write_json", "read_json"]

RECORD = 10      #: float64 values per journal record


def write_json(file, doc, durable=False):
    """Replace ``file`` with ``doc`` as JSON, atomically (a temporary file
    and ``os.replace``: a reader sees the old or the new whole file, never a
    part); ``durable`` fsyncs before the rename (power cuts)."""
    tmp = file + ".tmp"
    with open(tmp, "w") as f:
        json.dump(doc, f, separators=(",", ":"))
        if durable:
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, file)


def read_json(file):
    """The JSON document in ``file``, or None if it is missing or unreadable."""
    try:
        with open(file) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


class Journal:
    """An append-only file of float64 records of ``width`` values, cut back
    to a checkpoint's count after a crash."""

    def __init__(self, file, width, durable=False):
        self.file, self.width, self.durable = file, int(width), durable
        self._f = None
        self.records = 0                 #: records written so far

    def new(self):
        """Start empty (a new run)."""
        self.close()
        self._f = open(self.file, "wb")
        self.records = 0

    def append(self, rows):
        rows = np.asarray(rows, dtype="<f8").reshape(-1, self.width)
        if self._f is None:
            self.reopen(self.records)
        self._f.write(rows.tobytes())
        self.records += len(rows)

    def flush(self):
        if self._f is not None:
            self._f.flush()
            if self.durable:
                os.fsync(self._f.fileno())

    def reopen(self, records):
        """Continue after ``records`` records (cutting off any later ones a
        crash left behind)."""
        self.close()
        self._f = open(self.file, "r+b" if os.path.exists(self.file) else "w+b")
        self._f.truncate(records * self.width * 8)
        self._f.seek(records * self.width * 8)
        self.records = records

    def read(self, records=None):
        """(N, width) array of the records (the first ``records``)."""
        self.flush()
        if not os.path.exists(self.file):
            return np.zeros((0, self.width))
        data = np.fromfile(self.file, dtype="<f8")
        data = data[:len(data) // self.width * self.width].reshape(-1, self.width)
        return data if records is None else data[:records]

    def close(self):
        if self._f is not None:
            self._f.close()
            self._f = None


class StateStore:
    """The state files of arm ``arm`` in directory ``path``; ``dof``: the
    arm's joints (the width of the trace journal's records; None: no trace
    journal)."""

    def __init__(self, path, arm, durable=False, dof=None):
        self.path, self.arm, self.durable = path, arm, durable
        os.makedirs(path, exist_ok=True)
        self.chunk_file = os.path.join(path, "%s.chunk.json" % arm)
        self.journal_file = os.path.join(path, "%s.beads" % arm)
        self.trace_file = os.path.join(path, "%s.trace" % arm)
        self.checkpoint_file = os.path.join(path, "%s.checkpoint.json" % arm)
        self._beads = Journal(self.journal_file, RECORD, durable)
        self._trace = Journal(self.trace_file, 1 + 2 * dof, durable) if dof else None

    @property
    def records(self):
        """Bead records journalled so far."""
        return self._beads.records

    @property
    def trace_records(self):
        """Trace records (knots) journalled so far."""
        return self._trace.records if self._trace is not None else 0

    # ------------------------------------------------------------ files
    def _write_json(self, file, doc):
        write_json(file, doc, self.durable)

    def save_chunk(self, identity, text):
        self._write_json(self.chunk_file, {"identity": list(identity), "text": text})

    def load_chunk(self):
        with open(self.chunk_file) as f:
            doc = json.load(f)
        return tuple(doc["identity"]), doc["text"]

    def save(self, checkpoint):
        """Write the checkpoint (it records how many records of each journal it covers)."""
        self._flush()
        checkpoint = dict(checkpoint, records=self.records, trace_records=self.trace_records)
        self._write_json(self.checkpoint_file, checkpoint)

    def load(self):
        """The last checkpoint, or None if there is none (or it is unreadable)."""
        return read_json(self.checkpoint_file)

    # ------------------------------------------------------------ journals
    def _journals(self):
        return [j for j in (self._beads, self._trace) if j is not None]

    def new_journal(self):
        """Start an empty deposit journal (a new run: A5, A4, an A1 that
        starts the chunk again).  The trace journal goes on: the motion
        between runs (an A7 before the A1) was executed too."""
        self._beads.new()

    def start_clean(self):
        """Start empty journals (a node without a checkpoint of this ROS run)."""
        for j in self._journals():
            j.new()

    def append(self, p0, p1, e_mm, line, layer, t):
        """Journal K beads: ``p0``, ``p1`` (K, 3) m; the rest (K,)."""
        self._beads.append(np.column_stack([np.asarray(p0, float), np.asarray(p1, float), np.asarray(e_mm, float),
                                            np.asarray(line, float), np.asarray(layer, float),
                                            np.asarray(t, float)]))

    def append_trace(self, rows):
        """Journal knots: rows (K, 1 + 2 dof) of (t, q, v)."""
        self._trace.append(rows)

    def _flush(self):
        for j in self._journals():
            j.flush()

    def reopen(self, records, trace_records=0):
        """Continue the journals after ``records`` beads and ``trace_records``
        knots (cutting off any later ones a crash left behind)."""
        self._beads.reopen(records)
        if self._trace is not None:
            self._trace.reopen(trace_records)

    def read_journal(self, records=None):
        """(N, RECORD) array of the bead journal (the first ``records`` records)."""
        return self._beads.read(records)

    def read_trace(self, records=None):
        """(N, 1 + 2 dof) array of the trace journal (the first ``records`` records)."""
        return self._trace.read(records)

    def close(self):
        for j in self._journals():
            j.close()
