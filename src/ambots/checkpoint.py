"""A firmware's durable state, so that a node killed at any moment (``kill
-9``) resumes where it stopped: no bead missing, none laid twice, no
command executed twice.  ROS-free.

Files in the state directory, per arm:

* ``<arm>.chunk.json``: the loaded chunk (identity and G-code text),
  written once per A5;
* ``<arm>.beads``: the deposit journal, append-only records of
  :data:`RECORD` float64 (p0 xyz, p1 xyz in m, world frame; filament mm;
  G-code line; layer; simulated time s);
* ``<arm>.checkpoint.json``: the runner's :meth:`~ambots.runner.ArmRunner.checkpoint`,
  the receiver's and sender's snapshots, the number of journal records it
  covers and the ROS run id.

Order of a step (the firmware's loop): journal the new beads, then write the
checkpoint (atomically: temporary file + ``os.replace``), then publish.
After a crash the journal is cut back to the records the checkpoint
covers, so beads of a step that was not checkpointed are laid again by the
resumed run, never twice.  ``fsync`` is optional (``durable=True``): a
killed process loses nothing the kernel has; a power cut needs it.
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


class StateStore:
    """The state files of arm ``arm`` in directory ``path``."""

    def __init__(self, path, arm, durable=False):
        self.path, self.arm, self.durable = path, arm, durable
        os.makedirs(path, exist_ok=True)
        self.chunk_file = os.path.join(path, "%s.chunk.json" % arm)
        self.journal_file = os.path.join(path, "%s.beads" % arm)
        self.checkpoint_file = os.path.join(path, "%s.checkpoint.json" % arm)
        self._journal = None
        self.records = 0                 #: journal records written so far

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
        """Write the checkpoint (it records how many journal records it covers)."""
        self._flush()
        checkpoint = dict(checkpoint, records=self.records)
        self._write_json(self.checkpoint_file, checkpoint)

    def load(self):
        """The last checkpoint, or None if there is none (or it is unreadable)."""
        return read_json(self.checkpoint_file)

    # ------------------------------------------------------------ journal
    def new_journal(self):
        """Start an empty deposit journal (a new run)."""
        self.close()
        self._journal = open(self.journal_file, "wb")
        self.records = 0

    def append(self, p0, p1, e_mm, line, layer, t):
        """Journal K beads: ``p0``, ``p1`` (K, 3) m; the rest (K,)."""
        rec = np.column_stack([np.asarray(p0, float), np.asarray(p1, float), np.asarray(e_mm, float),
                               np.asarray(line, float), np.asarray(layer, float), np.asarray(t, float)])
        if self._journal is None:
            self.reopen(self.records)
        self._journal.write(rec.astype("<f8").tobytes())
        self.records += len(rec)

    def _flush(self):
        if self._journal is not None:
            self._journal.flush()
            if self.durable:
                os.fsync(self._journal.fileno())

    def reopen(self, records):
        """Continue the journal after ``records`` records (cutting off any
        later ones a crash left behind)."""
        self.close()
        mode = "r+b" if os.path.exists(self.journal_file) else "w+b"
        self._journal = open(self.journal_file, mode)
        self._journal.truncate(records * RECORD * 8)
        self._journal.seek(records * RECORD * 8)
        self.records = records

    def read_journal(self, records=None):
        """(N, RECORD) array of the journal (the first ``records`` records)."""
        self._flush()
        if not os.path.exists(self.journal_file):
            return np.zeros((0, RECORD))
        data = np.fromfile(self.journal_file, dtype="<f8")
        data = data[:len(data) // RECORD * RECORD].reshape(-1, RECORD)
        return data if records is None else data[:records]

    def close(self):
        if self._journal is not None:
            self._journal.close()
            self._journal = None
