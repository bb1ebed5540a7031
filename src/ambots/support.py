"""Support material for the built-in slicer (:class:`ambots.slicer.BuiltinSlicer`).

Per layer, all in manifold3d CrossSections (mm, bed frame), no loop per point:

overhang
  the part of layer i not within ``h tan(support_angle_deg)`` of layer
  i - 1 (the model's slope there is steeper than the angle from vertical);
  slivers thinner than a quarter bead are dropped.
bridge
  an overhang island anchored on the layer below at two or more places,
  every point of it within ``bridge_max_mm / 2`` of the layer below, is a
  bridge and gets no support; the slicer lays its solid infill across the
  gap, from the largest anchor towards the next.
support area
  projected down from every overhang to the bed or to the part: going down
  layer by layer, ``demand[i] = (demand[i + 1] - model[i]) | overhang[i + 1]``
  (what lies under the model stops there), printed as
  ``demand[i] - offset(model[i], support_xy_gap_mm)``, clipped to the part's
  prism (``keep``: the half-planes of :class:`ambots.partition.Part`).
interface
  the support within ``support_interface_layers`` layers under an overhang
  is dense (lines one bead spacing apart, across the sparse lines); the rest
  is sparse (lines ``support_spacing_mm`` apart, the same direction on every
  layer so that they stack).  Every support island also gets one loop round
  its edge, which carries the ends of the lines above it.
z gap
  the contact layer (the support right under an overhang) is printed
  ``support_z_gap_mm`` lower than its layer, with a bead that much thinner,
  so that the overhang is laid on it with a gap it can be broken off at.

The geometry of the overhangs and of the obstacles comes from the *whole*
placed model; only the printed area is clipped to the part's prism, so a
cut between two arms' parts creates no overhang and no support runs into
the neighbour's part.
"""
import math
from typing import List, NamedTuple, Optional

import manifold3d
import numpy as np

__all__ = ["SupportLayer", "overhangs", "support_layers", "prism", "SUPPORT", "SUPPORT_INTERFACE"]

#: G-code feature names, as PrusaSlicer writes them after ``;TYPE:``
SUPPORT = "Support material"
SUPPORT_INTERFACE = "Support material interface"

#: islands of support smaller than this (mm^2) are not printed
_MIN_AREA_MM2 = 0.05


class SupportLayer(NamedTuple):
    """The support of one layer: ``contact`` paths (printed ``z_gap`` lower,
    under the next layer's overhangs) and ``paths`` (at the layer's height),
    each a list of :class:`ambots.slicer.Path`; ``area`` the CrossSection
    of all of it."""
    contact: list
    paths: list
    area: object


def _empty():
    return manifold3d.CrossSection()


def _opened(cs, r):
    """``cs`` without the parts thinner than 2 r (morphological opening)."""
    if cs.is_empty():
        return cs
    return cs.offset(-r, manifold3d.JoinType.Miter).offset(r, manifold3d.JoinType.Miter)


def overhangs(outlines, settings):
    """Overhangs of every layer: (``over``, ``bridges``).

    ``over``: a list of L CrossSections, the overhangs that need support
    (the first is empty: layer 0 lies on the bed).  ``bridges``: a list of L
    lists of (CrossSection, angle_rad), the overhang islands that are
    bridges and the direction from one anchor to the other (the solid
    infill there is laid that way, across the gap).

    ``outlines``: the whole model's cross-section per layer (L CrossSections,
    mm) on the slicer's layer grid.
    """
    s = settings
    reach = s.layer_height_mm * math.tan(math.radians(s.support_angle_deg))
    over, bridges = [_empty()], [[]]
    for i in range(1, len(outlines)):
        cur, below = outlines[i], outlines[i - 1]
        spans = []
        bridges.append(spans)
        if cur.is_empty():
            over.append(_empty())
            continue
        found = _opened(cur - below.offset(reach, manifold3d.JoinType.Round), s.bead_width_mm / 4.0)
        if found.is_empty() or below.is_empty():
            over.append(found)
            continue
        keep = []
        for isl in found.decompose():
            if isl.area() <= _MIN_AREA_MM2:
                continue
            angle = _bridge_angle(isl, below, s)
            if angle is None:
                keep.append(isl)
            else:
                spans.append((isl, angle))
        over.append(manifold3d.CrossSection.batch_boolean(keep, manifold3d.OpType.Add) if keep else _empty())
    return over, bridges


def _bridge_angle(island, below, s):
    """If the overhang ``island`` spans a gap of at most ``bridge_max_mm`` (it
    touches the layer ``below`` at two or more separate places and no point
    of it is further than ``bridge_max_mm / 2`` from the layer below): the
    direction (rad) from the centroid of its largest anchor to that of the
    next largest; else None."""
    touch = island.offset(s.bead_width_mm, manifold3d.JoinType.Round) ^ below
    anchors = sorted((a for a in touch.decompose() if a.area() > _MIN_AREA_MM2), key=lambda a: -a.area())
    if len(anchors) < 2:
        return None
    far = island - below.offset(s.bridge_max_mm / 2.0, manifold3d.JoinType.Round)
    if not (far.is_empty() or far.area() < _MIN_AREA_MM2):
        return None
    (x0, y0), (x1, y1) = _centroid(anchors[0]), _centroid(anchors[1])
    return math.atan2(y1 - y0, x1 - x0)


def _centroid(cs):
    """Area centroid (x, y) of a CrossSection (mm), from its polygons
    (holes wound the other way, so the shoelace sums handle them)."""
    a = cx = cy = 0.0
    for p in cs.to_polygons():
        p = np.asarray(p, float)
        q = np.roll(p, -1, axis=0)
        c = p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]
        a += c.sum() / 2.0
        cx += ((p[:, 0] + q[:, 0]) * c).sum() / 6.0
        cy += ((p[:, 1] + q[:, 1]) * c).sum() / 6.0
    return (cx / a, cy / a) if a else (0.0, 0.0)


def prism(keep, outlines):
    """The part's prism as a CrossSection: the bounding square of
    ``outlines`` (with a margin) cut to the half-planes ``keep`` ([(n, offset)],
    kept side n . p >= offset, n's z ignored); None when ``keep`` is empty."""
    if not keep:
        return None
    boxes = [o.bounds() for o in outlines if not o.is_empty()]
    lo = np.min([b[:2] for b in boxes], axis=0) - 10.0
    hi = np.max([b[2:] for b in boxes], axis=0) + 10.0
    box = manifold3d.CrossSection.square((hi - lo).tolist()).translate(lo.tolist())
    size = float(np.max(hi - lo)) * 4.0
    for n, off in keep:
        n2 = np.asarray(n, float)[:2]
        n2 = n2 / np.linalg.norm(n2)
        t = np.array([-n2[1], n2[0]])
        c = n2 * off                      # a point on the line
        half = np.array([c + t * size, c + t * size + n2 * size,
                         c - t * size + n2 * size, c - t * size])
        if np.cross(half[1] - half[0], half[2] - half[1]) < 0:
            half = half[::-1]
        box = box ^ manifold3d.CrossSection([half.tolist()])
    return box


def support_layers(outlines, heights, settings, keep=None, over=None):
    """The support of every layer, from the whole model's ``outlines``.

    Parameters
    ----------
    outlines : list of L manifold3d.CrossSection
      The whole placed model per layer (mm).
    heights : (L,) float, mm
      Layer thicknesses.
    settings : ambots.slicer.SliceSettings
    keep : list of (n (3,), offset) or None
      The part's prism (its kept side n . p >= offset); None: the whole bed.
    over : list of L CrossSection or None
      :func:`overhangs` of ``outlines`` (its first item) if already found.

    Returns
    -------
    list of L :class:`SupportLayer` (or None where a layer has no support)
    """
    from ambots.slicer import Path, hatch, chain_lanes
    s = settings
    n = len(outlines)
    if not s.support or n < 2:
        return [None] * n
    if over is None:
        over = overhangs(outlines, s)[0]
    if all(o.is_empty() for o in over):
        return [None] * n
    clip = prism(keep, outlines)
    w = s.bead_width_mm
    angle = math.radians(s.infill_angle_deg)
    out: List[Optional[SupportLayer]] = [None] * n
    demand = _empty()
    for i in range(n - 2, -1, -1):
        demand = (demand - outlines[i]) + over[i + 1]
        area = demand - outlines[i].offset(s.support_xy_gap_mm, manifold3d.JoinType.Round)
        if clip is not None:
            area = area ^ clip
        area = _opened(area, w / 2.0)
        if area.is_empty() or area.area() < _MIN_AREA_MM2:
            continue
        h = float(heights[i])
        contact = area ^ over[i + 1] if i > 0 else _empty()
        near = [over[j] for j in range(i + 1, min(n, i + 1 + s.support_interface_layers))]
        dense = area ^ manifold3d.CrossSection.batch_boolean(near, manifold3d.OpType.Add)
        dense = dense - contact
        sparse = area - dense - contact
        layer_paths, contact_paths = [], []
        for region, spacing, feature, target, turn in (
                (contact, s.bead_spacing_mm(h - s.support_z_gap_mm), SUPPORT_INTERFACE, contact_paths, 1),
                (dense, s.bead_spacing_mm(h), SUPPORT_INTERFACE, layer_paths, 1),
                (sparse, s.support_spacing_mm, SUPPORT, layer_paths, 0)):
            region = _opened(region, w / 4.0)
            if region.is_empty() or region.area() < _MIN_AREA_MM2:
                continue
            ring = region.offset(-w / 2.0, manifold3d.JoinType.Miter)
            target += [Path(feature, np.asarray(p, float), True) for p in ring.to_polygons() if len(p) >= 3]
            inner = region.offset(-w / 2.0 - min(spacing, s.bead_spacing_mm(h)) / 2.0, manifold3d.JoinType.Miter)
            if inner.is_empty():
                continue
            # zig-zag lanes: a jump to the next line up to 1.5 spacings is extruded
            lines = chain_lanes(hatch(inner.to_polygons(), angle + turn * math.pi / 2.0, spacing,
                                      min_length=w / 2.0), 1.5 * spacing)
            target += [Path(feature, p, False) for p in lines]
        if layer_paths or contact_paths:
            out[i] = SupportLayer(contact_paths, layer_paths, area)
    return out
