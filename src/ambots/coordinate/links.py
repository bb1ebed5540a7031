"""Links along a band edge, shared by both concurrent strategies.

Where coordination cuts a layer into bands (:mod:`~ambots.coordinate.banded`)
or chunks (:mod:`~ambots.coordinate.timeline`) by distance to a seam plane,
a zig-zag of infill that crossed a band edge is cut there: each piece then
starts and ends at rest, with a retracted travel to the next.  The slicer
joins its lines at an outline with a short extruded link; :func:`edge_links`
makes that link at the band edge instead, where the slicer's path left the
band across the edge and came back across the same edge.  The pieces on the
other side of the edge are linked between the same points, so the two
sides' links meet end to end along it (as at a seam,
:func:`ambots.seam_clip.clip_paths`).

A link lies on one band edge, between two ends of pieces of the same band
(or chunk): its distance to every plane lies between its ends', so it moves
nothing of the band's footprint nearer a seam.  Millimetres, bed frame."""
import math

import numpy as np

__all__ = ["edge_links", "LayerWalls", "EDGE_LINK_MAX_MM"]

#: the longest link along a band edge (mm): the built-in slicer links its
#: sparse infill lines within 3 spacings (6.1 mm at 20 %,
#: :data:`ambots.slicer.SPARSE_LINK_SPACINGS`); at 45 deg to an edge the
#: lines of 20 % infill meet it 2.9 mm apart, of solid infill 0.64 mm
EDGE_LINK_MAX_MM = 6.0


def edge_links(layer_segs, pieces, src, planes, edges, features, walls=None):
    """One band's (or chunk's) pieces of a layer, in the slicer's order
    (``src``: the index in ``layer_segs``, the layer's sliced segments, of
    the segment each piece is, or was cut from), with an extruded link
    along a band edge wherever the slicer's infill path left the band
    across an edge and came back across the same edge.  ``planes``: [(n,
    offset)] the seam planes; ``edges``: for each plane, the distances (mm)
    from it at which bands meet; ``walls``: the layer's :class:`LayerWalls`,
    shared by the calls for its bands (made here if None).

    A link is made when the path between its ends was one run of extrusion
    of infill (``features``: :class:`~ambots.coordinate.steps.Features` of
    the sliced G-code; none known: no link), both ends lie on the same edge
    of the same plane, at most :data:`EDGE_LINK_MAX_MM` apart, and the link
    crosses no extrusion of the layer (a wall between them: a hole or
    another island; all of a call's links are tested at once).  The link
    lays as much filament a millimetre as the piece before it."""
    if len(pieces) < 2 or features is None or not len(features.starts):
        return pieces
    from ambots.slicer import crossing
    edges = [np.asarray(e, dtype=float) for e in edges]
    links = []                            # (the piece it follows, a, b, gap)
    for k, (prev, cur, i0, i1) in enumerate(zip(pieces[:-1], pieces[1:], src[:-1], src[1:])):
        a, b = prev.end, cur.start
        gap = math.hypot(a[0] - b[0], a[1] - b[1])
        if (prev.extrude and cur.extrude and i1 > i0 and a != b and a[2] == b[2] and gap <= EDGE_LINK_MAX_MM
                and _on_same_edge(a, b, planes, edges)
                and all(layer_segs[j].extrude and layer_segs[j].start == layer_segs[j - 1].end
                        for j in range(i0 + 1, i1 + 1))
                and features.infill(layer_segs[i0].line) and features.infill(layer_segs[i1].line)):
            links.append((k, a, b, gap))
    if not links:
        return pieces
    A = np.array([a[:2] for _, a, _, _ in links], dtype=float)
    B = np.array([b[:2] for _, _, b, _ in links], dtype=float)
    u = (B - A) * (1e-3 / np.array([g for *_, g in links]))[:, None]   # the lines that end there touch it there
    wall, boxes = (walls or LayerWalls(layer_segs)).get()
    blocked = crossing(A + u, B - u, wall, boxes)
    made = {}
    for (k, a, b, gap), no in zip(links, blocked.tolist()):
        if not no:
            prev = pieces[k]
            length = math.dist(prev.start, prev.end)
            made[k] = prev._replace(start=a, end=b, e=prev.e * gap / length if length > 0 else 0.0)
    out = [pieces[0]]
    for k, cur in enumerate(pieces[1:]):
        if k in made:
            out.append(made[k])
        out.append(cur)
    return out


class LayerWalls:
    """A layer's extrusions ((p, 2, 2) xy segments, mm) and their boxes, the
    walls a link along a band edge must not cross (:func:`edge_links`):
    made on first use, once for all the calls of the layer's bands or
    chunks (the four-arm cell's timeline made them again for each chunk:
    4,749 times on a 240 x 40 mm block)."""

    def __init__(self, layer_segs):
        self.segs, self._made = layer_segs, None

    def get(self):
        """(walls, their boxes as :func:`ambots.slicer.wall_boxes` gives them)."""
        if self._made is None:
            from ambots.slicer import wall_boxes
            ext = [s for s in self.segs if s.extrude and s.start != s.end]
            walls = np.array([[s.start[:2], s.end[:2]] for s in ext], dtype=float).reshape(-1, 2, 2)
            self._made = (walls, wall_boxes(walls))
        return self._made


def _on_same_edge(a, b, planes, edges):
    """Whether points ``a`` and ``b`` (mm) both lie on one band edge of the
    same plane of ``planes`` (``edges[p]``: plane p's edges, distances)."""
    for (n, off), e in zip(planes, edges):
        if not len(e):
            continue
        da = float(np.dot(n, a) - off)
        db = float(np.dot(n, b) - off)
        if abs(da - db) < 1e-6 and np.abs(e - abs(da)).min() < 1e-6:
            return True
    return False
