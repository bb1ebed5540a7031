"""The look-ahead order of a scheduled timeline's chunks (:func:`layer_orders`).

The greedy schedule (:class:`~ambots.coordinate.schedule.Schedule`) starts,
whenever an arm is free, the chunk nearest a seam that nobody is in the way
of.  It does not look ahead: the small chunks at the centre, near every
seam, are left for the end of the layer, where the arms take them in turn
and wait.  Here each layer is a small scheduling problem first:

* the jobs are the arms' chunks of the layer, each with its duration at
  the feedrates plus :data:`RUN_S` for every run of extrusion in it (a
  travel and the ramps of a start from rest);
* two chunks of adjacent arms *conflict* when their footprints (closest
  distances to the arms' plane) come within the pair's zone; so does a
  chunk with the point where an adjacent arm stands still after its last
  chunk (its *end*: the chunk's point farthest from the seams, where the
  schedule ends it, :meth:`~ambots.coordinate.timeline.Seams.clearance`), and
  an arm's travel from the end of its previous chunk;
* a *list schedule* runs the layer: an arm that is free starts the first
  chunk in its order that conflicts with nothing the others are doing.

A local search (:data:`SEARCH_SWAPS` moves of one chunk to another place
in its arm's order, kept when the layer's list schedule is no longer; from
two starting orders) finds each layer's orders; the schedule then ranks
the chunks by them.  Session 24, the four-arm 300 mm plate, one chunk band
per seam: the layers' list schedules sum to 13,800 s against 13,189 s for
the slowest arm's work in each layer (feed-time seconds); the greedy
schedule on the same chunks 17,454 s.

Units: mm, s."""
import random

import numpy as np

from ambots.coordinate.steps import seg_times

__all__ = ["layer_orders", "RUN_S", "SEARCH_SWAPS"]

#: what a run of extrusion costs besides its feed time (s): a travel to it
#: and the ramps from rest (:func:`~ambots.coordinate.schedule._path_time`
#: counts 0.1 s and the travel at 150 mm/s)
RUN_S = 0.15
#: moves tried by the local search per layer and starting order
SEARCH_SWAPS = 300


class _Layer:
    """One layer's chunks as a scheduling problem: ``arm`` (K,) each job's
    arm (an index), ``dur`` (K,) s, and the conflicts (K, K) bool between
    jobs of different arms: ``ff`` footprint with footprint, ``fe`` (i, j)
    job i's footprint with the end of job j, ``ee`` end with end;
    ``chunk`` (K,) each job's index among its arm's chunks (its rank's
    key).  :func:`_layer` makes one from a timeline's chunks."""

    def __init__(self, arm, dur, ff, fe, ee, chunk=None):
        self.arm, self.dur = np.asarray(arm, dtype=int), np.asarray(dur, dtype=float)
        self.ff, self.fe, self.ee = (np.asarray(m, dtype=bool) for m in (ff, fe, ee))
        # the same as lists of lists for :meth:`makespan`, which asks them millions of
        # times one pair at a time (numpy's scalar indexing: 15 M calls, 9.5 s of the
        # four-arm cell's 148 s planning a 240 x 40 mm block, in one process)
        self._ff, self._fe, self._ee = (m.tolist() for m in (self.ff, self.fe, self.ee))
        self.chunk = np.arange(len(self.arm)) if chunk is None else np.asarray(chunk, dtype=int)
        self.by_arm = {}
        for k, a in enumerate(self.arm.tolist()):
            self.by_arm.setdefault(a, []).append(k)

    def key(self):
        """What makes two layers the same problem (sparse infill repeats)."""
        return (self.arm.tobytes(), np.round(self.dur, 1).tobytes(), self.ff.tobytes(), self.fe.tobytes(),
                self.ee.tobytes())

    def bound(self):
        """The slowest arm's work (s): no order does the layer faster."""
        return max((float(self.dur[jobs].sum()) for jobs in self.by_arm.values()), default=0.0)

    def makespan(self, orders):
        """The list schedule of ``orders`` ({arm index: [job]}): its length
        (s), inf if the arms would stand in each other's way for ever."""
        ff, fe, ee = self._ff, self._fe, self._ee
        todo = {a: list(o) for a, o in orders.items()}
        last = {a: None for a in orders}
        running = {}                         # arm -> (job, end time, the arm's job before)
        t = end = 0.0

        def clash(a, i):
            p = last[a]
            for b, q in last.items():
                if b == a:
                    continue
                if b in running:
                    j, _, q = running[b]
                    if ff[i][j] or (p is not None and fe[j][p]):
                        return True
                if q is not None and (fe[i][q] or (p is not None and ee[p][q])):
                    return True
            return False

        while running or any(todo.values()):
            for a, o in todo.items():
                if a not in running:
                    k = next((k for k, i in enumerate(o) if not clash(a, i)), None)
                    if k is not None:
                        i = o.pop(k)
                        running[a] = (i, t + self.dur[i], last[a])
            if not running:
                return float("inf")
            t = min(e for _, e, _ in running.values())
            for a in [a for a, (_, e, _) in running.items() if e <= t + 1e-12]:
                last[a] = running.pop(a)[0]
                end = t
        return end


def _layer(seams, chunks, layer):
    """A timeline's chunks of ``layer`` (:func:`~ambots.coordinate.timeline.
    _chunks`) as a :class:`_Layer`: each chunk's duration at the feedrates
    plus :data:`RUN_S` a run, its footprint, and its end (the point of the
    chunk clearest of the seams, :meth:`~ambots.coordinate.timeline.Seams.
    clearance`)."""
    names = seams.names
    arm, chunk, dur, fp, end = [], [], [], [], []
    for a, n in enumerate(names):
        for ci, (ps, dmin, _) in enumerate(chunks.get((n, layer), [])):
            starts = np.array([p.start for p in ps], dtype=float)
            ends = np.array([p.end for p in ps], dtype=float)
            runs = 1 + int(np.count_nonzero(np.any(starts[1:] != ends[:-1], axis=1)))
            pts = np.concatenate([starts, ends])
            arm.append(a)
            chunk.append(ci)
            dur.append(float(seg_times(starts, ends, [p.e for p in ps], [p.feedrate for p in ps]).sum())
                       + RUN_S * runs)
            fp.append(np.asarray(dmin, dtype=float))
            end.append(seams.dist(n, pts[int(np.argmax(seams.clearance(n, pts)))][None])[0])
    K = len(arm)
    ff, fe, ee = (np.zeros((K, K), dtype=bool) for _ in range(3))
    jobs = {}
    for k, a in enumerate(arm):
        jobs.setdefault(a, []).append(k)
    for a, n in enumerate(names):
        for i, b in enumerate(seams.nbrs[n]):
            ja, jb = jobs.get(a, []), jobs.get(names.index(b), [])
            if not ja or not jb:
                continue
            j, zone = seams.where[n][b], seams.Z[n][i] - 1e-9
            fa, fb = np.array([fp[k][i] for k in ja]), np.array([fp[k][j] for k in jb])
            ea, eb = np.array([end[k][i] for k in ja]), np.array([end[k][j] for k in jb])
            rows, cols = np.ix_(ja, jb)
            ff[rows, cols] = fa[:, None] + fb[None, :] < zone
            fe[rows, cols] = fa[:, None] + eb[None, :] < zone
            ee[rows, cols] = ea[:, None] + eb[None, :] < zone
    return _Layer(arm, dur, ff, fe, ee, chunk)


def _search(layer, start, swaps, rng):
    """Local search from the orders ``start``: (orders, makespan)."""
    best = {a: list(o) for a, o in start.items()}
    value = layer.makespan(best)
    movable = [a for a, o in best.items() if len(o) > 1]
    for _ in range(swaps if movable else 0):
        a = rng.choice(movable)
        cand = dict(best)
        o = cand[a] = list(best[a])
        i, j = rng.sample(range(len(o)), 2)
        o.insert(j, o.pop(i))
        v = layer.makespan(cand)
        if v <= value:
            best, value = cand, v
    return best, value


def layer_orders(seams, chunks, n_layers, swaps=SEARCH_SWAPS, seed=0):
    """{(arm, layer): {chunk index: rank}} for
    :class:`~ambots.coordinate.schedule.Schedule`'s ``order``, and the
    sums over layers of (the list schedules' makespans, their bounds) (s).
    ``chunks``: :func:`~ambots.coordinate.timeline._chunks`.  The same
    layer twice gets the same orders; the search is seeded (the same
    chunks always give the same orders)."""
    rng = random.Random(seed)
    found, out = {}, {}
    total = bound = 0.0
    for layer in range(n_layers):
        problem = _layer(seams, chunks, layer)
        key = problem.key()
        if key not in found:
            level = lambda i: chunks[seams.names[problem.arm[i]], layer][problem.chunk[i]][2]
            starts = [{a: sorted(o, key=lambda i: (level(i), sign * problem.dur[i])) for a, o in problem.by_arm.items()}
                      for sign in (-1.0, 1.0)]          # nearest a seam first, the longest / shortest first
            found[key] = min((_search(problem, s, swaps, rng) for s in starts), key=lambda r: r[1])
        orders, value = found[key]
        total += value
        bound += problem.bound()
        for a, o in orders.items():
            ranks = out.setdefault((seams.names[a], layer), {})
            for r, i in enumerate(o):
                ranks[int(problem.chunk[i])] = r
    return out, (total, bound)
