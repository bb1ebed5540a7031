"""Banded sweeps: concurrent programs for arms whose adjacency has two
colours (two arms; a row of arms along a beam).  Each layer is cut into
bands by distance from the nearest seam, and the two colours sweep the
bands in opposite directions (:func:`banded_programs`; the bands' number
and edges: :mod:`ambots.coordinate.bands`)."""
import numpy as np

from ambots.coordinate.bands import _phase_of, band_stats, choose_bands
from ambots.coordinate.emit import ArmProgram, Emitter, resolve_waits
from ambots.coordinate.links import LayerWalls, edge_links
from ambots.coordinate.parking import APPROACH_MM, lift_height
from ambots.coordinate.steps import END, Step, Wait, _order_runs, close, cut_segment
from ambots.coordinate.zones import distance_to_planes, planes_at

__all__ = ["banded_programs"]


def banded_programs(arms, read, park, n_layers, zone_mm, planes, colour, adjacent, home=None, zones=None,
                    moves=None, opening=None):
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
    done, lifted straight up first as high as the A7 needs to keep clear
    of the bed and the part (:func:`~ambots.coordinate.parking.lift_height`
    with ``moves``, :class:`~ambots.coordinate.parking.JointMoves`; 10 mm
    over the part without).  ``opening``: {arm: [messages]} its program
    sends before anything else (A7 to the cell's idle arms).  Returns the programs, or None when an arm with no work in a band
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
    lo = inner_limits(names, bounds, adjacent, pair_zone, k)
    phases = _phases(arms, segs_by, planes, bounds, k, colour, n_layers, lo,
                     {a.name: read[a.name].features for a in arms})
    parks_first, park_waits = _banded_start(arms, names, phases, planes, adjacent, home, n_layers, k, lo,
                                            pair_zone)
    ends = np.array([s.end for segs in segs_by.values() for s in segs if s.extrude], dtype=float).reshape(-1, 3)
    top = float(ends[:, 2].max()) if len(ends) else 0.0
    box = ((tuple(ends[:, :2].min(axis=0)) + (0.0,), tuple(ends[:, :2].max(axis=0)) + (top,)) if len(ends)
           else ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    emitters = {}
    for a in arms:
        em = Emitter(a, "concurrent", ["; seam zone %.1f mm, %d band(s) per layer from %s mm, colour %d"
                                       % (zone_mm, k, " ".join("%.3f" % v for v in bounds[a.name]), colour[a.name])])
        nb = [o for o in arms if o.name in adjacent[a.name]]
        if (opening or {}).get(a.name):
            em.step(Step(directives=list(opening[a.name])))
        if parks_first[a.name]:
            em.step(Step(park=park[a.name], report=nb[0].id, mark="parked"))
        em.step(Step(waits=[Wait(other, "parked") for other in park_waits[a.name]]))
        last = max([layer for layer in range(n_layers) for p in range(k) if phases[a.name, layer, p][1]] or [-1])
        clear = lambda: lift_height(moves, a.name, em.pos, park[a.name], top + APPROACH_MM, box)  # noqa: E731
        lift = None
        for layer in range(n_layers):
            for p in range(k):
                if not _sweep_step(em, a, arms, phases, planes, bounds, nb, layer, p, k):
                    return None
            if layer == last and em.pos is not None:
                # its last layer with work: the neighbours may print on, higher (a ramp's
                # tall end), for long; it lifts straight up at once, clear of the whole
                # part, and goes through the layers left (their waits and reports, and
                # moving aside from its seams where a band needs it) up there
                lift = clear()
                em.step(Step(lift_to=lift))
        if n_layers and (colour[a.name] + n_layers - 1) % 2 == 0:
            # this arm ends the last layer away from its seams and its neighbours at
            # them: it parks only when they are done (a joint move to the park
            # position is not a straight line, and it would pass them at work)
            em.step(Step(waits=[Wait(other.name, END) for other in nb]))
        # clear of the part (lifted above, or now), then to the park position
        if lift is None and em.pos is not None:
            lift = clear()
        em.step(Step(park=park[a.name], lift_to=lift))
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
        approach.travel = _retreat(em.pos, planes_at(planes, a.name, layer), band, bounds[a.name])
        if approach.travel is None:           # no point of this band clear of all its seams: not banded
            return False
    if p > 0 and not towards and nb:
        # tell the neighbours (A10 with position, via the hub) that the approach is done
        approach.report = nb[0].id
    em.step(approach)
    em.step(Step(pieces=segs))
    return True


def inner_limits(names, bounds, adjacent, zones, k):
    """{arm: (k,) mm}: how near its nearest seam each band's work may come.
    Band i of arm a runs while each adjacent arm c works in its band
    k-1-i, and their edges keep ``t_a[i] + t_c[k-1-i] >= zone``; the slack
    is shared: ``lo_a[i] = t_a[i] - slack / 2`` (all of it where the other
    band is c's first, which has no inner edge: ``lo_a[k-1] = zone``), so
    ``lo_a[i] + lo_c[k-1-i] >= zone`` still holds.  Work may lie farther
    from the seam than its band (that only widens the gap), and as near as
    this."""
    out = {}
    for a in names:
        t = np.asarray(bounds[a], dtype=float)
        lo = t.copy()
        for i in range(1, k):
            need = []
            for c in adjacent[a]:
                tc, zone = float(bounds[c][k - 1 - i]), float(zones[a, c])
                need.append(zone if tc <= 0.0 else t[i] - max(t[i] + tc - zone, 0.0) / 2.0)
            if need:
                lo[i] = min(t[i], max(need))
        out[a] = lo
    return out


#: a run of extrusions that crosses band edges this many times or more (a
#: zig-zag lane of infill) is cut between its lines, where the run's work
#: would be divided among the bands, not at every crossing (each piece starts
#: and stops at rest and takes a travel: on the demo block with the edge 59.9 mm
#: from the seam, 1,345 -> 603 runs of extrusion per arm)
ZIGZAG_CROSSINGS = 3
#: ... and only when no band's work changes by more than this share of the
#: run's length (lines too near the seam for their band are cut at the
#: crossings, and their pieces count where they fall): on the demo's lanes
#: 0.037-0.042; on the hex plate's, whose lines span the whole part, 0.16
#: for some (2 arms took 15,204 s with those divided, 12,622 s cut)
ZIGZAG_SHIFT = 0.1


def _phases(arms, segs_by, planes, bounds, k, colour, n_layers, lo=None, features=None):
    """{(arm, layer, phase): (band, pieces)}: each arm's segments cut at its
    band edges (:func:`_cut_layer`; ``lo``: :func:`inner_limits`), by the
    phase in which it prints them, with links along the edges
    (:func:`~ambots.coordinate.links.edge_links`; ``features``: {arm: the
    features of its sliced G-code, :class:`~ambots.coordinate.steps.Features`,
    or None})."""
    features = features or {}
    phases = {}
    for a in arms:
        for layer in range(n_layers):
            layer_segs = segs_by.get((a.name, layer), [])
            here = planes_at(planes, a.name, layer)
            segs, mids, fixed, src = _cut_layer(layer_segs, here, bounds[a.name], None if lo is None else lo[a.name])
            band = np.where(fixed >= 0, fixed, _band_of(mids, here, bounds[a.name])).tolist()
            by_band = [[] for _ in range(k)]
            by_src = [[] for _ in range(k)]
            for s, b, i in zip(segs, band, src):
                by_band[b].append(s)
                by_src[b].append(i)
            if len(bounds[a.name]) > 1 and here:
                edges = [bounds[a.name][1:]] * len(here)
                walls = LayerWalls(layer_segs)
                by_band = [edge_links(layer_segs, pieces, idx, here, edges, features.get(a.name), walls)
                           for pieces, idx in zip(by_band, by_src)]
            for b in range(k):
                phases[a.name, layer, _phase_of(b, colour[a.name], layer, k)] = (b, by_band[b])
    return phases


def _cut_layer(segs, planes, t, lo=None):
    """A layer's segments cut at the band edges ``t`` (:func:`_split_at_bands`),
    the pieces' midpoints (P, 3), and the band of each piece (P,) where it
    is set (-1: the band of its midpoint).  Only the segments that an edge
    comes within 1e-6 mm of are cut one by one: on the others the cut would
    find nothing (a layer has tens of thousands of segments on a large
    model, and the per-segment numpy calls were most of the coordination's
    time).  With ``lo`` (:func:`inner_limits`), zig-zag runs keep their
    segments whole (:func:`_zigzag_bands`)."""
    if not segs:
        return [], np.zeros((0, 3)), np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    P0 = np.array([s.start for s in segs], dtype=float)
    P1 = np.array([s.end for s in segs], dtype=float)
    mids = np.add(P0, P1) / 2.0
    if not planes or len(t) < 2:
        return list(segs), mids, np.full(len(segs), -1), np.arange(len(segs))
    flag = np.zeros(len(segs), dtype=bool)
    for n, off in planes:
        fa, fb = P0 @ np.asarray(n, dtype=float) - off, P1 @ np.asarray(n, dtype=float) - off
        low, high = np.minimum(fa, fb) - 1e-6, np.maximum(fa, fb) + 1e-6
        for edge in t[1:]:
            flag |= (low < edge) & (edge < high)
    if not flag.any():
        return list(segs), mids, np.full(len(segs), -1), np.arange(len(segs))
    # every segment an edge comes near, cut once: its pieces and their midpoints
    cuts = {i: _split_at_bands(segs[i], planes, t) for i in np.flatnonzero(flag).tolist()}
    cut_mids = {i: np.array([np.add(p.start, p.end) / 2.0 for p in ps]) for i, ps in cuts.items()}
    whole = (_zigzag_bands(segs, P0, P1, mids, flag, planes, t, lo, cuts, cut_mids) if lo is not None
             else np.full(len(segs), -1))
    out, src, extra, fixed = [], [], [], []
    for i, (s, f) in enumerate(zip(segs, flag.tolist())):
        if not f or whole[i] >= 0:
            out.append(s)
            src.append(i)
            fixed.append(whole[i])
            continue
        out += cuts[i]
        src += [-1 - i] * len(cuts[i])
        fixed += [-1] * len(cuts[i])
        extra.append(cut_mids[i])
    src = np.array(src)
    cut = src < 0
    out_mids = np.empty((len(out), 3))
    out_mids[~cut] = mids[src[~cut]]
    out_mids[cut] = np.concatenate(extra).reshape(-1, 3) if extra else np.zeros((0, 3))
    return out, out_mids, np.array(fixed, dtype=int), np.where(cut, -1 - src, src)


def _zigzag_bands(segs, P0, P1, mids, flag, planes, t, lo, cuts, cut_mids):
    """The band (S,) of each segment of a zig-zag run that is printed whole
    (-1: cut at the edges as usual; ``cuts``/``cut_mids``: {flagged
    segment: its pieces cut at the edges / their midpoints}).  A run of
    extrusions (each starting
    where the one before ends) that crosses the edges
    :data:`ZIGZAG_CROSSINGS` times or more, and whose bands rise (or fall)
    along it, is divided at its vertices: its first segments, as long as
    the run's work in band 0 when cut at every crossing, go to band 0, the
    next as long as its work in band 1 to band 1, and so on (lengths).  A segment
    keeps that band if it lies no nearer the seam than the band's limit
    ``lo`` (:func:`inner_limits`; farther is always allowed), else it is
    cut at the edges as before, and its pieces count in their bands' shares
    (the bands up to b take whole segments until they hold their share).
    A run whose bands would hold more than :data:`ZIGZAG_SHIFT` of its
    length more or less than when cut at every crossing is cut so."""
    k = len(t)
    out = np.full(len(segs), -1)
    ext = np.array([s.extrude for s in segs]) & np.any(P0 != P1, axis=1)
    joined = np.zeros(len(segs), dtype=bool)
    joined[1:] = ext[1:] & ext[:-1] & np.all(P0[1:] == P1[:-1], axis=1)
    first = np.flatnonzero(ext & ~joined)
    if not len(first):
        return out
    last = np.concatenate([first[1:], [len(segs)]])
    ends = np.array([i0 + 1 + int(np.argmin(np.concatenate([joined[i0 + 1:i1], [False]]))) for i0, i1 in
                     zip(first, last)])
    runs = [(i0, i1) for i0, i1 in zip(first, ends) if flag[i0:i1].sum() >= ZIGZAG_CROSSINGS]
    if not runs:
        return out
    d = np.minimum(distance_to_planes(P0, planes).min(axis=1), distance_to_planes(P1, planes).min(axis=1))
    length = np.linalg.norm(P1 - P0, axis=1)
    band = _band_of(mids, planes, t)
    lo = np.asarray(lo, dtype=float)
    # each segment's length per band when cut at every crossing (S, k)
    per_band = np.zeros((len(segs), k))
    per_band[np.arange(len(segs)), band] = length
    for i, ps in cuts.items():
        per_band[i] = np.bincount(_band_of(cut_mids[i], planes, t),
                                  [float(np.linalg.norm(np.subtract(p.end, p.start))) for p in ps], minlength=k)
    for i0, i1 in runs:
        idx = np.arange(i0, i1)
        work = per_band[idx].sum(axis=0)          # the run's work per band, cut at every crossing
        half = len(idx) // 2
        rise = band[idx[half:]].mean() - band[idx[:half]].mean()
        if rise == 0:
            continue                              # a loop, or no trend: cut at the crossings
        order = idx if rise > 0 else idx[::-1]
        # along the run, band b takes whole segments until the bands up to b hold their
        # share; a segment too near the seam for the band is cut at the crossings (its
        # pieces count where they fall)
        goal = np.cumsum(work)
        held = np.zeros(k)
        b = 0
        whole = {}
        for i in order:
            while b < k - 1 and held[:b + 1].sum() + length[i] / 2.0 > goal[b]:
                b += 1
            if d[i] >= lo[b] - 1e-9:
                whole[i] = b
                held[b] += length[i]
            else:
                held += per_band[i]
        if np.abs(held - work).max() > ZIGZAG_SHIFT * length[idx].sum():
            continue            # its lines too long for the bands' slack: cut at every crossing
        for i, vb in whole.items():
            out[i] = vb
    return out


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


def _banded_start(arms, names, phases, planes, adjacent, home, n_layers, k, limits, zones):
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
    home_d = {a.name: distance_to_planes(np.asarray(home[a.name], dtype=float)[None],
                                         planes_at(planes, a.name, 0))[0]
              for a in arms}
    for a in arms:
        for i, b in enumerate(nb[a.name]):
            j = nb[b].index(a.name)
            lo = limits[b][first[b][2]] if first[b] is not None else np.inf
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
