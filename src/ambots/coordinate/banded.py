"""Banded sweeps: concurrent programs for arms whose adjacency has two
colours (two arms; a row of arms along a beam).  Each layer is cut into
bands by distance from the nearest seam, and the two colours sweep the
bands in opposite directions (:func:`banded_programs`; the bands' number
and edges: :mod:`ambots.coordinate.bands`)."""
import numpy as np

from ambots.coordinate.bands import _phase_of, band_stats, choose_bands
from ambots.coordinate.emit import ArmProgram, Emitter, resolve_waits
from ambots.coordinate.steps import END, Step, Wait, _order_runs, close, cut_segment
from ambots.coordinate.zones import distance_to_planes

__all__ = ["banded_programs"]


def banded_programs(arms, read, park, n_layers, zone_mm, planes, colour, adjacent, home=None, zones=None):
    """Two colours (every seam between adjacent arms separates a colour-0
    from a colour-1 arm).  ``planes[arm]``: the planes (n, o) between the
    arm and its adjacent arms; ``zone_mm``: the largest zone of an adjacent
    pair; ``zones``: {(a, b): mm} each adjacent pair's own (default: all
    ``zone_mm``).  Only adjacent arms wait for each other.

    Each arm's work is cut into k bands by distance from its nearest seam:
    band i is [t[i], t[i+1]) (t[0] = 0), band k-1 the rest; each arm has its
    own boundaries t.  In phase i of a layer one colour prints band i while
    the other prints band k-1-i, so two adjacent arms a, b are always at
    least t_a[i] + t_b[k-1-i] apart across their seam, which the boundaries
    keep >= the pair's zone for every i.  Boundaries: either equal widths w
    >= zone / (k-1) (w = the arm's reach from its nearest seam / k when that
    is wider), or each arm's own work split into k equal shares, raised
    where a pair needs it (:func:`~ambots.coordinate.bands._balanced_bounds`;
    in a row of arms along a beam the parts between two seams reach half as
    far from their nearest seam as the ones at the ends); ``k`` (2..12) and
    the kind are chosen to minimise the estimated makespan
    (:func:`~ambots.coordinate.bands.choose_bands`).  Directions alternate with the layer
    (even layers: colour 0 moves away from the seam, colour 1 towards it;
    odd layers the reverse), so no arm ever crosses another's path at a
    layer change.  Between phases the arm moving away first travels to its
    next band (its *approach*, reported with an A3), and the arm moving
    towards the seam waits for that (an A9 on the approach line) before it
    approaches; an arm with no work in its next band still moves there (a
    retreat), so the spacing holds whatever the timing.  That is the only
    wait: an arm moving away only widens the gap, so it goes on at once (it
    can get at most one phase ahead: at the next layer it moves towards the
    seam and waits).  At the end, the arms that finish away from their
    seams park only when their neighbours (which finish at the seams) are
    done.  Returns the programs, or None when an arm with no work in a band
    cannot retreat into it without coming nearer than the band to another
    of its seams (:func:`_retreat`)."""
    names = [a.name for a in arms]
    if zones is None:
        zones = {}
    pair_zone = {(a, b): float(zones.get((a, b), zone_mm)) for a in names for b in adjacent[a]}
    segs_by = {(a.name, k): segs for a in arms for k, segs in read[a.name][1].items()}
    # choose k and the band edges on the segments cut into pieces of at most 5 mm
    stats = band_stats(arms, segs_by, planes, n_layers)
    k, bounds = choose_bands(arms, stats, n_layers, zone_mm, colour, adjacent, pair_zone)
    phases = _phases(arms, segs_by, planes, bounds, k, colour, n_layers)
    parks_first, park_waits = _banded_start(arms, names, phases, planes, adjacent, home, n_layers, k, bounds,
                                            pair_zone)
    emitters = {}
    for a in arms:
        em = Emitter(a, "concurrent", ["; seam zone %.1f mm, %d band(s) per layer from %s mm, colour %d"
                                       % (zone_mm, k, " ".join("%.3f" % v for v in bounds[a.name]), colour[a.name])])
        nb = [o for o in arms if o.name in adjacent[a.name]]
        if parks_first[a.name]:
            em.step(Step(park=park[a.name], report=nb[0].id, mark="parked"))
        em.step(Step(waits=[Wait(other, "parked") for other in park_waits[a.name]]))
        for layer in range(n_layers):
            for p in range(k):
                if not _sweep_step(em, a, arms, phases, planes, bounds, nb, layer, p, k):
                    return None
        if n_layers and (colour[a.name] + n_layers - 1) % 2 == 0:
            # this arm ends the last layer away from its seams and its neighbours at
            # them: it parks only when they are done (a joint move to the park
            # position is not a straight line, and it would pass them at work)
            em.step(Step(waits=[Wait(other.name, END) for other in nb]))
        em.step(Step(park=park[a.name]))           # lift clear of the part, then go to the park position
        emitters[a.name] = em
    resolve_waits(emitters)
    return {a.name: ArmProgram(a, "concurrent", emitters[a.name].lines, read[a.name][0], n_layers, k, start_first=True,
                                 events=emitters[a.name].events())
            for a in arms}


def _sweep_step(em, a, arms, phases, planes, bounds, nb, layer, p, k):
    """Phase p of ``layer`` of arm ``a``: the approach to its band (a wait
    first when it moves towards the seam; a report after it when it moves
    away), then the band's pieces.  False if the arm has no work in the band
    and cannot retreat into it (:func:`_retreat`)."""
    band, segs = phases[a.name, layer, p]
    if planes[a.name] or len(arms) > 1:        # drop slicer travels, shortest-travel order
        segs = _order_runs(segs, em.pos)
    approach = Step(mark=(layer, p))
    if p == 0:
        zs = [s.end[2] for q in range(k) for s in phases[a.name, layer, q][1]]
        approach.layers = [zs[-1] if zs else 0.0]
    towards = p > 0 and band < phases[a.name, layer, p - 1][0]
    if towards:       # wait until the neighbours moving away have approached their band
        approach.waits = [Wait(other.name, (layer, p)) for other in nb]
    first = next((s for s in segs if s.start != s.end), None)
    if first is not None:
        approach.travel = first.start
    elif p > 0 and not towards and em.pos is not None:
        approach.travel = _retreat(em.pos, planes[a.name], band, bounds[a.name])
        if approach.travel is None:           # no point of this band clear of all its seams: not banded
            return False
    if p > 0 and not towards and nb:
        # tell the neighbours (A10 with position, via the hub) that the approach is done
        approach.report = nb[0].id
    em.step(approach)
    em.step(Step(pieces=segs))
    return True


def _phases(arms, segs_by, planes, bounds, k, colour, n_layers):
    """{(arm, layer, phase): (band, pieces)}: each arm's segments cut at its
    band edges, by the phase in which it prints them."""
    phases = {}
    for a in arms:
        for layer in range(n_layers):
            segs, mids = _cut_layer(segs_by.get((a.name, layer), []), planes[a.name], bounds[a.name])
            band = _band_of(mids, planes[a.name], bounds[a.name]).tolist()
            by_band = [[] for _ in range(k)]
            for s, b in zip(segs, band):
                by_band[b].append(s)
            for b in range(k):
                phases[a.name, layer, _phase_of(b, colour[a.name], layer, k)] = (b, by_band[b])
    return phases


def _cut_layer(segs, planes, t):
    """A layer's segments cut at the band edges ``t`` (:func:`_split_at_bands`)
    and the pieces' midpoints (P, 3).  Only the segments that an edge comes
    within 1e-6 mm of are cut one by one: on the others the cut would find
    nothing (a layer has tens of thousands of segments on a large model, and
    the per-segment numpy calls were most of the coordination's time)."""
    if not segs:
        return [], np.zeros((0, 3))
    P0 = np.array([s.start for s in segs], dtype=float)
    P1 = np.array([s.end for s in segs], dtype=float)
    mids = np.add(P0, P1) / 2.0
    if not planes or len(t) < 2:
        return list(segs), mids
    flag = np.zeros(len(segs), dtype=bool)
    for n, off in planes:
        fa, fb = P0 @ np.asarray(n, dtype=float) - off, P1 @ np.asarray(n, dtype=float) - off
        lo, hi = np.minimum(fa, fb) - 1e-6, np.maximum(fa, fb) + 1e-6
        for edge in t[1:]:
            flag |= (lo < edge) & (edge < hi)
    if not flag.any():
        return list(segs), mids
    out, src, extra = [], [], []
    for i, (s, f) in enumerate(zip(segs, flag.tolist())):
        if not f:
            out.append(s)
            src.append(i)
            continue
        for piece in _split_at_bands(s, planes, t):
            out.append(piece)
            src.append(-1)
            extra.append(np.add(piece.start, piece.end) / 2.0)
    src = np.array(src)
    cut = src < 0
    out_mids = np.empty((len(out), 3))
    out_mids[~cut] = mids[src[~cut]]
    out_mids[cut] = np.array(extra, dtype=float).reshape(-1, 3)
    return out, out_mids


def _split_at_bands(seg, planes, t):
    """Cut a segment where its distance to any seam plane crosses a band
    boundary ``t[1:]`` (mm, increasing; band i is [t[i], t[i+1]), the last
    band the rest); E is shared in proportion to length."""
    a, b = np.array(seg.start, dtype=float), np.array(seg.end, dtype=float)
    if not planes or close(seg.start, seg.end):
        return [seg]
    cuts = []
    for n, off in planes:
        fa, fb = float(n @ a - off), float(n @ b - off)
        if abs(fb - fa) < 1e-12:
            continue
        lo, hi = sorted((fa, fb))
        for edge in t[1:]:
            if lo < edge < hi:
                u = (edge - fa) / (fb - fa)
                if 1e-9 < u < 1 - 1e-9:
                    cuts.append(u)
    return cut_segment(seg, cuts)


def _band_of(mids, planes, t):
    """Band index (S,) of each segment from its midpoint ``mids`` (S, 3)
    distance to the nearest seam; band i is [t[i], t[i+1]) (mm), the last
    band the rest."""
    k = len(t)
    if not planes:
        return np.full(len(mids), k - 1)
    if not len(mids):
        return np.zeros(0, dtype=int)
    d = distance_to_planes(mids, planes).min(axis=1)
    return np.clip(np.searchsorted(np.asarray(t), d, side="right") - 1, 0, k - 1).astype(int)


def _banded_start(arms, names, phases, planes, adjacent, home, n_layers, k, bounds, zones):
    """How the banded programs start.  An arm leaves home at once for its
    first band, unless it has no work in the first phase (it would wait at
    home) or its home is in the way of an adjacent arm's first step (home
    and first band nearer than the zone across their plane): then it first
    goes to its park position and reports (A3), and the adjacent arms whose
    first step it was in the way of wait for that report before they move.
    Returns ({arm: parks first}, {arm: [arms to wait for]})."""
    nb = {a.name: [b for b in names if b in adjacent[a.name]] for a in arms}
    first = {}
    for a in arms:
        first[a.name] = next(((layer, p, phases[a.name, layer, p][0]) for layer in range(n_layers) for p in range(k)
                              if any(s.extrude and s.start != s.end for s in phases[a.name, layer, p][1])), None)
    parks_first = {a.name: first[a.name] is not None and first[a.name][:2] != (0, 0) for a in arms}
    waits = {a.name: [] for a in arms}
    if home is None:
        return parks_first, waits
    home_d = {a.name: distance_to_planes(np.asarray(home[a.name], dtype=float)[None], planes[a.name])[0]
              for a in arms}
    for a in arms:
        for i, b in enumerate(nb[a.name]):
            j = nb[b].index(a.name)
            lo = bounds[b][first[b][2]] if first[b] is not None else np.inf
            if home_d[a.name][i] + min(lo, home_d[b][j]) < zones[a.name, b] - 1e-9:
                parks_first[a.name] = True
                waits[b].append(a.name)
    for a in arms:
        if parks_first[a.name] and not nb[a.name]:
            parks_first[a.name] = False
    return parks_first, {n: sorted(set(v), key=names.index) for n, v in waits.items()}


def _retreat(pos, planes, band, t):
    """A point on the same side as ``pos`` just inside ``band`` (mm; band i
    is [t[i], t[i+1])), moving away from the nearest seam; None if that
    brings it nearer than the band to another of its seams (an arm between
    two seams whose zones together are about as wide as its part)."""
    p = np.array(pos, dtype=float)
    if not planes:
        return tuple(p)
    d = distance_to_planes(p[None], planes)[0]
    j = int(np.argmin(d))
    n = np.asarray(planes[j][0], dtype=float)
    width = t[band + 1] - t[band] if band + 1 < len(t) else 8.0
    want = t[band] + min(2.0, width / 4)
    if d[j] >= want:
        return tuple(p)
    q = p + n * (want - d[j])
    q = np.array([q[0], q[1], p[2]])
    if distance_to_planes(q[None], planes)[0].min() < t[band] - 1e-6:
        return None
    return (float(q[0]), float(q[1]), float(p[2]))
