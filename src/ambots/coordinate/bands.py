"""How many bands per layer a banded program has, and where their edges
are (:func:`choose_bands`): the choice that minimises the estimated
makespan, on every arm's work cut into pieces of at most 5 mm
(:func:`band_stats`).

Band i of an arm is [t[i], t[i+1]) (mm of distance from its nearest seam,
t[0] = 0), band k-1 the rest.  In phase i of a layer one colour prints
band i while the other prints band k-1-i (:func:`_phase_of`)."""
import numpy as np

from ambots.coordinate.steps import seg_times
from ambots.coordinate.zones import distance_to_planes, planes_at

__all__ = ["choose_bands", "band_stats", "PIECE_S"]

#: what a piece of path costs besides its time at the feedrate when the bands
#: cut it out of its neighbours (s), relative to the estimate's feed times: a
#: retracted travel to it, and the ramps from rest and to rest at its ends.
#: Fitted on the demo's two-arm plans timed by the one timing law
#: (:mod:`ambots.estimate`) for five band layouts (3 to 12 bands, equal and
#: balanced): makespan = 1.19 x (feed time estimate) + 0.20 s x (pieces on
#: the critical phases), so 0.20 / 1.19 = 0.17 here (0.3 before: too few
#: bands, 3 of 77 mm on the demo, 8,933 s against 8,710 s with 5 balanced)
PIECE_S = 0.17
#: the estimated makespans (s) and k of the last banded programs, by kind of band edges, for inspection
_last_bands = None
# (balanced edges once had to beat equal widths by 5 %, then 1 %: that kept
# the demo on 3 equal bands although 5 balanced ones were 2.5 % faster, and
# on 2 bands of 60 mm, 5,157 s, against 5,032 s with a 52 mm near band.  The
# estimate counts the waits at the barriers now, :data:`SYNC_MARGIN`, and
# the least estimate wins.)


def band_stats(arms, segs_by, planes, n_layers):
    """{(arm, layer): (distance to the nearest seam (S,), duration (S,),
    follows (S,))} of the arm's segments on the layer cut into pieces of at
    most 5 mm (midpoint distance, duration), vectorised: a long line along
    the seam's normal (a perimeter along a beam) spreads over many bands.
    ``follows``: the piece follows on from the one before (no travel
    between them): same segment, or the segment before ends where it starts."""
    stats = {}
    for a in arms:
        for layer in range(n_layers):
            segs = segs_by.get((a.name, layer), [])
            if not segs:
                continue
            P0 = np.array([s.start for s in segs], dtype=float)
            P1 = np.array([s.end for s in segs], dtype=float)
            dur = seg_times(P0, P1, [s.e for s in segs], [s.feedrate for s in segs])
            pieces = np.maximum(1, np.ceil(np.linalg.norm(P1 - P0, axis=1) / 5.0)).astype(int)
            seg = np.repeat(np.arange(len(segs)), pieces)
            frac = (np.arange(len(seg)) - np.repeat(np.cumsum(pieces) - pieces, pieces) + 0.5) / pieces[seg]
            mid = P0[seg] + frac[:, None] * (P1 - P0)[seg]
            here = planes_at(planes, a.name, layer)
            d = distance_to_planes(mid, here).min(axis=1) if here else np.full(len(seg), np.inf)
            joined = np.zeros(len(segs), bool)
            joined[1:] = np.all(P1[:-1] == P0[1:], axis=1)
            follows = np.ones(len(seg), bool)
            follows[0] = False
            first_piece = np.cumsum(pieces) - pieces
            follows[first_piece] = joined
            stats[a.name, layer] = (d, dur[seg] / pieces[seg], follows)
    return stats


def _reach(arms, stats, n_layers):
    """({arm: its reach from its nearest seam (mm)}, {arm: (distances
    (S,), cumulative share of the work (S,)) of all its pieces within a
    finite distance of a seam, nearest first}, or None for an arm without
    such work).  Sorted once here: every band count and near share
    (:func:`_balanced_bounds`) splits the same order (sorting it again for
    each was 0.66 of choose_bands' 1.15 s on a 100 mm sphere)."""
    far = {}
    for a in arms:
        ds = [float(np.max(d[np.isfinite(d)])) for (n, _), (d, _, _) in stats.items()
              if n == a.name and np.isfinite(d).any()]
        far[a.name] = max(ds or [0.0])
    work = {}
    for a in arms:
        ds = [stats[a.name, layer] for layer in range(n_layers) if (a.name, layer) in stats]
        d = np.concatenate([x for x, _, _ in ds]) if ds else np.zeros(0)
        dur = np.concatenate([y for _, y, _ in ds]) if ds else np.zeros(0)
        d, dur = d[np.isfinite(d)], dur[np.isfinite(d)]
        if not len(d) or dur.sum() <= 0:
            work[a.name] = None
            continue
        order = np.argsort(d)
        work[a.name] = (d[order], np.cumsum(dur[order]) / dur.sum())
    return far, work


def _uniform_bounds(arms, far, zone_mm, k):
    """Equal widths w >= zone / (k-1) (the arm's reach from its nearest seam / k when that is wider)."""
    out = {}
    for a in arms:
        w = max(max(zone_mm, 1e-3) / (k - 1), far[a.name] / k)
        out[a.name] = np.arange(k) * w
    return out


#: the arms that sweep towards the seam are counted as arriving this much
#: (a share of the time) earlier than their estimate at each barrier, where
#: they wait for the arms sweeping away: the arms differ in speed (the
#: Kinova takes 1.7 % longer than the UR10 on the demo) and the estimate
#: errs by a few per cent per phase, so bands that tie in the estimate make
#: the arm moving towards the seam wait (on the demo 143-236 s per arm with
#: two equal bands; 0 with a narrower near band)
SYNC_MARGIN = 0.05
#: the near band's share of an arm's work, relative to 1/k, of the balanced
#: edges tried (:func:`_balanced_bounds`)
NEAR_SHARES = (1.0, 0.85, 0.7)


def _estimate(arms, stats, colour, n_layers, k, t):
    """Estimated makespan (s) of k bands with edges ``t`` {arm: (k,)}: per
    layer, from both colours starting it together, the arms sweeping away
    from the seam print their bands one after the other; an arm sweeping
    towards it starts each phase after its last one and after the arms
    sweeping away have ended their phases before it (the barrier; their
    times counted ``1 + SYNC_MARGIN`` there); the layer ends when the last
    arm is done.  Every piece of path a band cuts out is counted with
    PIECE_S, and half a second a barrier."""
    return _estimate_groups(_Groups(arms, _layer_groups(arms, stats, n_layers), colour), k, t)


def _layer_groups(arms, stats, n_layers):
    """The layers of ``stats`` grouped by content and parity (a part's
    sparse infill repeats every other layer): [(how many, a layer, {arm:
    stats})], so an estimate costs one evaluation per distinct layer."""
    groups = {}
    for layer in range(n_layers):
        key = [layer % 2]
        for a in arms:
            st = stats.get((a.name, layer))
            key.append(None if st is None else (st[0].tobytes(), st[1].tobytes(), st[2].tobytes()))
        key = tuple(key)
        if key in groups:
            groups[key][0] += 1
        else:
            groups[key] = [1, layer, {a.name: stats[a.name, layer] for a in arms if (a.name, layer) in stats}]
    return [tuple(g) for g in groups.values()]


class _Groups:
    """:func:`_layer_groups` laid out for :func:`_estimate_groups`: per arm,
    the pieces of all groups one after the other (distances, durations,
    follows, group index, first piece of each group) and whether the arm
    sweeps away from the seam in each group, so an estimate is a few numpy
    calls whatever the number of layers."""

    def __init__(self, arms, groups, colour):
        self.counts = [count for count, _, _ in groups]
        self.n = len(groups)
        self.arms = {}
        for a in arms:
            rows = [(g, by_arm[a.name]) for g, (_, _, by_arm) in enumerate(groups) if a.name in by_arm]
            if not rows:
                continue
            sizes = [len(st[0]) for _, st in rows]
            group = np.repeat([g for g, _ in rows], sizes)
            first = np.zeros(len(group), dtype=bool)
            first[np.cumsum([0] + sizes[:-1])] = True
            away = np.array([(colour[a.name] + layer) % 2 == 0 for _, layer, _ in groups])
            self.arms[a.name] = (np.concatenate([st[0] for _, st in rows]), np.concatenate([st[1] for _, st in rows]),
                                 np.concatenate([st[2] for _, st in rows]), group, first, away)


def _estimate_groups(groups, k, t):
    """:func:`_estimate` on :class:`_Groups` (the same sums in the same order
    as one layer group at a time)."""
    phases = {}
    for name, (d, dur, follows, group, first, away) in groups.arms.items():
        band = np.clip(np.searchsorted(t[name], d, side="right") - 1, 0, k - 1)
        # every piece of path a band cuts out starts and ends at rest, with a travel
        fresh = ~follows
        change = np.zeros(len(band), dtype=bool)
        change[1:] = band[1:] != band[:-1]
        fresh |= change & ~first
        cell = group * k + band
        per_band = (np.bincount(cell, weights=dur, minlength=groups.n * k)
                    + PIECE_S * np.bincount(cell, weights=fresh, minlength=groups.n * k)).reshape(groups.n, k)
        phases[name] = (np.where(away[:, None], per_band, per_band[:, ::-1]), away)
    # the arms sweeping away: each phase's end, the latest of them (with the margin: the barriers)
    ends = np.zeros((groups.n, k))
    barrier = np.zeros((groups.n, k))
    for ph, away in phases.values():
        done = np.where(away[:, None], np.cumsum(ph, axis=1), 0.0)
        np.maximum(ends, done, out=ends)
        np.maximum(barrier, done * (1.0 + SYNC_MARGIN), out=barrier)
    layer_t = ends[:, -1].copy()
    for ph, away in phases.values():               # the arms sweeping towards the seam
        e = np.zeros(groups.n)
        for p in range(k):
            e = (np.maximum(e, barrier[:, p - 1]) if p else e) + ph[:, p]
        np.maximum(layer_t, np.where(away, 0.0, e), out=layer_t)
    est = 0.0
    for count, row in zip(groups.counts, layer_t):
        est += count * (row + k * 0.5)                # a barrier costs about half a second
    return est


def choose_bands(arms, stats, n_layers, zone_mm, colour, adjacent, pair_zone):
    """(k, {arm: band edges (k,)}): k in 2..12 and equal widths or balanced
    shares (:func:`_balanced_bounds`), whichever has the least estimated
    makespan (ties: equal widths)."""
    global _last_bands
    names = [a.name for a in arms]
    far, work = _reach(arms, stats, n_layers)
    groups = _Groups(arms, _layer_groups(arms, stats, n_layers), colour)
    best = {}
    for k in range(2, 13):
        tries = [("uniform", _uniform_bounds(arms, far, zone_mm, k))]
        tries += [("balanced", _balanced_bounds(names, work, adjacent, pair_zone, k, near)) for near in NEAR_SHARES]
        for kind, t in tries:
            if t is None:
                continue
            est = _estimate_groups(groups, k, t)
            if kind not in best or est < best[kind][0] - 1e-9:
                best[kind] = (est, k, t)
    kind = "balanced" if "balanced" in best and best["balanced"][0] < best["uniform"][0] else "uniform"
    _last_bands = {kd: (est, k) for kd, (est, k, _) in best.items()}
    return best[kind][1], best[kind][2]


def _phase_of(band, colour, layer, k):
    """Phase in which an arm of ``colour`` prints ``band`` on ``layer``."""
    away = (colour + layer) % 2 == 0          # this arm sweeps away from the seam on this layer
    return band if away else k - 1 - band


def _balanced_bounds(names, work, adjacent, zones, k, near=1.0):
    """Band boundaries {arm: (k,) mm} that split each arm's work (``work``:
    {arm: (distance to the nearest seam (S,), cumulative share of the work
    (S,)), nearest first, or None}, :func:`_reach`) into k shares, the near
    band's ``near`` / k and the others equal, then raised until every
    adjacent pair a, b keeps t_a[i] + t_b[k-1-i] >= its zone for every i
    (t[0] = 0 stays; raising a boundary only moves work to lower bands, and
    only widens the gaps)."""
    t = {}
    for n in names:
        if work[n] is None:
            t[n] = np.zeros(k)
            continue
        d, cum = work[n]
        share = [near / k + (i - 1) * (1.0 - near / k) / (k - 1) for i in range(1, k)]
        q = [0.0] + [float(d[min(int(np.searchsorted(cum, c)), len(d) - 1)]) for c in share]
        t[n] = np.maximum.accumulate(np.maximum(np.array(q), 0.0))
    return t if _raise(t, names, adjacent, zones, k) else None


def _raise(t, names, adjacent, zones, k):
    """Raise the band edges ``t`` {arm: (k,)} (in place) until every
    adjacent pair a, b keeps t_a[i] + t_b[k-1-i] >= its zone for every i
    (t[0] = 0 stays; raising an edge only moves work to lower bands, and
    only widens the gaps); True if they do."""
    for _ in range(10 * k * len(names) + 10):
        changed = False
        for a in names:
            for b in adjacent[a]:
                z = zones[a, b]
                for i in range(k):
                    j = k - 1 - i
                    short = z - (t[a][i] + t[b][j])
                    if short <= 1e-9:
                        continue
                    changed = True
                    if i == 0:
                        t[b][j] += short
                    elif j == 0:
                        t[a][i] += short
                    else:
                        t[a][i] += short / 2
                        t[b][j] += short / 2
                t[a] = np.maximum.accumulate(t[a])
                t[b] = np.maximum.accumulate(t[b])
        if not changed:
            break
    return all(t[a][i] + t[b][k - 1 - i] >= zones[a, b] - 1e-6 for a in names for b in adjacent[a] for i in range(k))
