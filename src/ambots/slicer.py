"""Slicing: a placed mesh (mm) -> G-code text, with two back ends.

``builtin`` (the default) needs no external program; ``prusa`` runs the
``prusa-slicer`` command line.  Both take the same :class:`SliceSettings`
and write G-code in the model's own frame: a model placed with
:func:`ambots.mesh.place_on_bed` keeps its x, y and z, so the G-code of the
two back ends can be compared (and cut) in one frame.  Millimetres
throughout: G-code is the mm boundary of the package (:mod:`ambots.units`).
:func:`choose_backend` says which back end ``auto`` means on this machine
(``prusa`` where ``prusa-slicer`` is installed, else ``builtin``) and which
PrusaSlicer version runs.

The built-in pipeline (:meth:`BuiltinSlicer.slice`) is a sequence of steps::

    layers      layer_heights, slice_layers   mesh -> one outline per layer
    regions     interior_regions, plan_island outline -> islands; the infill area
                                              of each, split into solid and sparse
    support     ambots.support                overhangs and bridges (of the whole
                                              model), support lines per layer
    perimeters  perimeter_loops               inward offsets of the outline
    infill      hatch, chain_lanes            clipped parallel lines, zig-zag lanes
    ordering    order_islands, order_paths    island order, seams, directions
    G-code      GcodeWriter                   travel, retraction, E, comments

Geometry is done by manifold3d (slices, offsets, booleans on
:class:`manifold3d.CrossSection`) and numpy (scan-line clipping, extrusion
amounts, text formatting); no Python loop runs per point.
"""
import dataclasses
import math
import os
import re
import shutil
import subprocess
import tempfile
from typing import NamedTuple, Optional

import manifold3d
import numpy as np

import ambots
from ambots.errors import AmbotsError, ConfigError
from ambots.mesh import to_manifold, source_name
from ambots.sliced import MoveRecord, SlicedText
from ambots.support import SUPPORT, SUPPORT_INTERFACE, overhangs, support_layers

#: G-code feature names, as PrusaSlicer writes them after ``;TYPE:``
EXTERNAL_PERIMETER = "External perimeter"
PERIMETER = "Perimeter"
SOLID_INFILL = "Solid infill"
SPARSE_INFILL = "Internal infill"
#: (support: SUPPORT = "Support material", SUPPORT_INTERFACE = "Support material interface")

#: config file of the ``prusa`` back end
DEFAULT_PRUSA_INI = ambots.data_path("config", "prusa", "ambots_pla.ini")


class SlicerError(AmbotsError):
    """A model could not be sliced (nothing to print, external slicer failed...)."""


# --------------------------------------------------------------- settings

@dataclasses.dataclass(frozen=True)
class SliceSettings:
    """What both back ends print.  Lengths in mm, feedrates in mm/min.

    The bead (one extruded line) is a rectangle with semicircular ends,
    ``bead_width_mm`` wide and one layer high, as in Slic3r/PrusaSlicer:
    see :meth:`bead_area_mm2` and :meth:`bead_spacing_mm`.
    """
    layer_height_mm: float = 0.2
    first_layer_height_mm: float = 0.2
    nozzle_diameter_mm: float = 0.4
    bead_width_mm: float = 0.45
    filament_diameter_mm: float = 1.75
    perimeters: int = 2
    #: sparse infill density, 0..1 (1 = solid)
    infill_density: float = 0.2
    #: direction of the infill lines of even layers; odd layers turn 90 deg
    infill_angle_deg: float = 45.0
    #: how far infill lines reach into the innermost perimeter (fraction of bead width)
    infill_overlap: float = 0.15
    top_solid_layers: int = 3
    bottom_solid_layers: int = 3
    perimeter_feedrate_mm_min: float = 2400.0
    external_perimeter_feedrate_mm_min: float = 1800.0
    infill_feedrate_mm_min: float = 4800.0
    solid_infill_feedrate_mm_min: float = 2400.0
    #: cap on every extrusion feedrate of the first layer
    first_layer_feedrate_mm_min: float = 1200.0
    travel_feedrate_mm_min: float = 7800.0
    z_feedrate_mm_min: float = 720.0
    retract_length_mm: float = 0.8
    retract_feedrate_mm_min: float = 2100.0
    #: travels shorter than this are not retracted
    retract_min_travel_mm: float = 2.0
    #: lift during retracted travels (0: none)
    z_hop_mm: float = 0.0
    #: nozzle temperature; None: the built-in back end writes no temperature
    #: command and the prusa back end keeps the .ini's
    nozzle_temperature_c: Optional[float] = None
    #: outline simplification tolerance
    resolution_mm: float = 0.0125
    #: print support under overhangs (:mod:`ambots.support`); a model without
    #: overhangs gets none either way
    support: bool = True
    #: overhangs steeper than this from vertical are supported (0 < angle < 90)
    support_angle_deg: float = 45.0
    #: overhangs spanning at most this between two anchors are bridged, not supported
    bridge_max_mm: float = 10.0
    #: distance between the lines of sparse support
    support_spacing_mm: float = 2.0
    #: dense layers at the top of the support (>= 1)
    support_interface_layers: int = 2
    #: the contact layer under an overhang is printed this much lower (0 <= gap < layer height)
    support_z_gap_mm: float = 0.1
    #: clearance between the support and the model beside it
    support_xy_gap_mm: float = 0.3
    support_feedrate_mm_min: float = 3000.0

    def __post_init__(self):
        def need(ok, field, message):
            if not ok:
                raise ConfigError("SliceSettings", field, message)
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None and f.name == "nozzle_temperature_c":
                continue
            if f.name == "support":
                need(isinstance(v, bool), f.name, "must be true or false, got %r" % (v,))
                continue
            need(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v),
                 f.name, "must be a finite number, got %r" % (v,))
        for name in ("layer_height_mm", "first_layer_height_mm", "nozzle_diameter_mm",
                     "bead_width_mm", "filament_diameter_mm", "perimeter_feedrate_mm_min",
                     "external_perimeter_feedrate_mm_min", "infill_feedrate_mm_min",
                     "solid_infill_feedrate_mm_min", "first_layer_feedrate_mm_min",
                     "travel_feedrate_mm_min", "z_feedrate_mm_min", "retract_feedrate_mm_min",
                     "resolution_mm", "support_spacing_mm", "support_feedrate_mm_min"):
            need(getattr(self, name) > 0, name, "must be > 0, got %r" % getattr(self, name))
        for name in ("perimeters", "top_solid_layers", "bottom_solid_layers"):
            v = getattr(self, name)
            need(int(v) == v and v >= 0, name, "must be a whole number >= 0, got %r" % v)
        need(int(self.support_interface_layers) == self.support_interface_layers
             and self.support_interface_layers >= 1, "support_interface_layers",
             "must be a whole number >= 1, got %r" % self.support_interface_layers)
        need(0 < self.support_angle_deg < 90, "support_angle_deg",
             "must be within 0..90 (exclusive), got %r" % self.support_angle_deg)
        need(0 <= self.support_z_gap_mm < min(self.layer_height_mm, self.first_layer_height_mm),
             "support_z_gap_mm", "must be >= 0 and below the layer height, got %r" % self.support_z_gap_mm)
        need(self.support_spacing_mm >= self.bead_width_mm, "support_spacing_mm",
             "must be at least bead_width_mm (%r), got %r" % (self.bead_width_mm, self.support_spacing_mm))
        for name in ("retract_length_mm", "retract_min_travel_mm", "z_hop_mm", "bridge_max_mm",
                     "support_xy_gap_mm"):
            need(getattr(self, name) >= 0, name, "must be >= 0, got %r" % getattr(self, name))
        need(0 <= self.infill_density <= 1, "infill_density",
             "must be within 0..1, got %r" % self.infill_density)
        need(0 <= self.infill_overlap <= 0.5, "infill_overlap",
             "must be within 0..0.5, got %r" % self.infill_overlap)
        for name in ("layer_height_mm", "first_layer_height_mm"):
            need(getattr(self, name) <= self.bead_width_mm, name,
                 "must not exceed bead_width_mm (%r)" % self.bead_width_mm)

    def bead_area_mm2(self, height_mm):
        """Cross-section of a bead of this width and ``height_mm``:
        ``(w - h) h + pi (h/2)^2`` (Slic3r's flow model)."""
        w, h = self.bead_width_mm, height_mm
        return (w - h) * h + math.pi * (h / 2.0) ** 2

    def bead_spacing_mm(self, height_mm):
        """Distance between the centre lines of touching beads,
        ``area / h = w - h (1 - pi/4)``: beads that far apart fill the layer."""
        return self.bead_area_mm2(height_mm) / height_mm

    @property
    def filament_area_mm2(self):
        """Cross-section of the filament, pi (d/2)^2."""
        return math.pi * (self.filament_diameter_mm / 2.0) ** 2


# ------------------------------------------------------------- interface

def slice_mesh(mesh, settings=None, backend="builtin", whole=None, keep=None, **options):
    """Slice ``mesh`` (mm, placed on the bed) and return the G-code text.

    Parameters
    ----------
    mesh : trimesh.Trimesh
      Closed volume in mm; z = 0 is the bed (nothing may lie below it).
    settings : SliceSettings or None
      ``None``: the defaults.
    backend : str
      ``"builtin"`` or ``"prusa"`` (see :data:`BACKENDS`).
    whole : trimesh.Trimesh, WholeModel or None
      When ``mesh`` is a part of a larger placed model (an arm's part of a
      job), that whole model (a :class:`WholeModel` is sliced once for all
      the parts): the built-in back end finds overhangs and
      keeps support clear of the model on it, so a cut makes no overhang.
      The prusa back end cannot take it (it supports each part on its own).
    keep : list of (n (3,), offset) or None
      The part's prism (:attr:`ambots.partition.Part.planes`, kept side
      n . p >= offset): the built-in back end prints the support there only.
    options
      Passed to the back end's constructor, e.g. ``ini_path=`` for prusa.
    """
    try:
        cls = BACKENDS[backend]
    except KeyError:
        raise SlicerError("unknown slicer back end %r; available: %s"
                          % (backend, ", ".join(sorted(BACKENDS)))) from None
    slicer = cls(settings, **options)
    if cls is BuiltinSlicer:
        return slicer.slice(mesh, whole=whole, keep=keep)
    return slicer.slice(mesh)


def _check_above_bed(mesh):
    z_min = float(mesh.bounds[0][2])
    if z_min < -1e-6:
        raise SlicerError("%s: extends %.3f mm below the bed (z = 0); place it on the "
                          "bed first (ambots.mesh.place_on_bed)" % (source_name(mesh), -z_min))


# ========================================================= built-in slicer

class Path(NamedTuple):
    """One extrusion: a feature name and the (n, 2) points it joins, in mm.
    A closed path (a perimeter loop) does not repeat its first point; the
    printer goes round and back to it, starting wherever is nearest."""
    feature: str
    points: np.ndarray
    closed: bool


class BuiltinSlicer:
    """Planar slicer in numpy and manifold3d: perimeters, rectilinear infill,
    solid top and bottom layers, support (:mod:`ambots.support`), retraction.
    No skirt or gap fill."""

    name = "builtin"

    def __init__(self, settings=None):
        self.settings = settings or SliceSettings()

    def slice(self, mesh, whole=None, keep=None):
        """G-code text (:class:`ambots.sliced.SlicedText`) for ``mesh``
        (trimesh.Trimesh, mm, on the bed); ``whole``, ``keep``: see
        :func:`slice_mesh`."""
        return self.write(self.toolpaths(mesh, whole, keep), source_name(mesh))

    def toolpaths(self, mesh, whole=None, keep=None):
        """Steps 1-4 for ``mesh``: one :class:`LayerPaths` per layer with
        something to print, from the bed up."""
        s = self.settings
        _check_above_bed(mesh)
        solid = to_manifold(mesh)
        # 1. layers: one outline per layer, cut at the middle of its height
        z_tops, heights = layer_heights(float(mesh.bounds[1][2]), s)
        outlines = slice_layers(solid, z_tops - heights / 2.0, s.resolution_mm)
        if all(o.is_empty() for o in outlines):
            raise SlicerError("%s: nothing to print at layer height %.3f mm (the model "
                              "is thinner than a layer)" % (source_name(mesh), s.layer_height_mm))
        # 2. regions: where each layer is covered above and below (-> sparse)
        interiors = interior_regions(outlines, s.bottom_solid_layers, s.top_solid_layers)
        # 2b. support, from the whole model (on its layer grid: the same
        # grid from the bed up), printed in the part's prism only
        # and bridges, whose solid infill is laid across the gap
        supports, bridges = [None] * len(outlines), [[]] * len(outlines)
        if s.support:
            if whole is None:
                ctx = WholeModel(mesh, s, (outlines, heights))
            else:
                ctx = whole if isinstance(whole, WholeModel) and whole.settings == s else WholeModel(
                    whole.mesh if isinstance(whole, WholeModel) else whole, s)
                if ctx.mesh is mesh:
                    ctx.seed(outlines, heights)      # the whole model itself: sliced once
            whole_outlines, whole_heights, over, spans = ctx.layers()
            supports = (support_layers(whole_outlines, whole_heights, s, keep, over) + supports)[:len(outlines)]
            bridges = (spans + bridges)[:len(outlines)]
        out = []
        for i, (z, h, outline, interior) in enumerate(zip(z_tops, heights, outlines, interiors)):
            sup = supports[i]
            if outline.is_empty() and sup is None:
                continue
            angle = math.radians(s.infill_angle_deg + 90.0 * (i % 2))
            islands = [plan_island(island, interior, h, angle, s, bridges[i])  # 3.-4. perimeters, infill
                       for island in outline.decompose()]
            out.append(LayerPaths(i, float(z), float(h), sup.contact if sup is not None else None,
                                  sup.paths if sup is not None else None, islands))
        return out

    def write(self, layers, name="model", clip=None):
        """Steps 5-6: G-code (:class:`ambots.sliced.SlicedText`) of
        ``layers`` (:meth:`toolpaths`); ``clip``: only what lies in this
        prism (:func:`ambots.seam_clip.clip_layer`), e.g. an arm's part of
        the whole model's toolpaths."""
        from ambots.seam_clip import at_layer, clip_layer
        s = self.settings
        writer = GcodeWriter(s, name)

        def links(height):
            sp = s.bead_spacing_mm(height)
            return {SOLID_INFILL: infill_link_mm(SOLID_INFILL, sp, s.bead_width_mm),
                    SPARSE_INFILL: infill_link_mm(SPARSE_INFILL, sp / max(s.infill_density, 1e-9), s.bead_width_mm)}
        for lp in layers:
            if clip is not None:
                lp = clip_layer(lp, at_layer(clip, lp.index), link_max=links(lp.height))   # plan_island's
                if lp is None:
                    continue
            z, h = lp.z, lp.height
            writer.layer_change(z, h, first=(lp.index == 0))
            if lp.support is not None:   # support first: the contact layer z_gap lower, then the rest
                if lp.contact:
                    writer.extrude_paths(order_paths(lp.contact, writer.xy), h - s.support_z_gap_mm,
                                         z=z - s.support_z_gap_mm)
                writer.set_z(z)
                writer.extrude_paths(order_paths(lp.support, writer.xy), h)
            # 5. ordering (from where the nozzle is at the layer change), then
            # 6. G-code, with travel and retraction
            writer.extrude_paths([path for paths in order_islands(lp.islands, writer.xy) for path in paths], h)
        return writer.finish()


class LayerPaths(NamedTuple):
    """One layer's toolpaths (:meth:`BuiltinSlicer.toolpaths`): its
    ``index`` from the bed, top ``z`` and ``height`` (mm), the support's
    contact paths and other paths (None: no support in this layer), and
    per island its groups of paths (:func:`plan_island`)."""
    index: int
    z: float
    height: float
    contact: Optional[list]
    support: Optional[list]
    islands: list


class WholeModel:
    """The whole placed model (trimesh, mm) that parts are cut from, sliced
    once for all of them: its outlines per layer, layer heights, overhangs
    and bridges (:func:`ambots.support.overhangs`), computed on first use.
    ``layers``: (outlines, heights) already sliced, if any."""

    def __init__(self, mesh, settings, layers=None):
        self.mesh, self.settings = mesh, settings
        self._layers = self._paths = self._text = None
        if layers is not None:
            self._layers = tuple(layers) + overhangs(layers[0], settings)

    def toolpaths(self):
        """The whole model's :class:`LayerPaths` (:meth:`BuiltinSlicer.toolpaths`),
        made once."""
        if self._paths is None:
            self._paths = BuiltinSlicer(self.settings).toolpaths(self.mesh, whole=self)
        return self._paths

    def text(self):
        """The whole model's G-code (:class:`ambots.sliced.SlicedText`), written once."""
        if self._text is None:
            self._text = BuiltinSlicer(self.settings).write(self.toolpaths(), source_name(self.mesh))
        return self._text

    def clipped(self, prism):
        """The G-code of the part of the whole model in ``prism``
        (:func:`ambots.seam_clip.prisms`): the whole model's toolpaths clipped."""
        return BuiltinSlicer(self.settings).write(self.toolpaths(), source_name(self.mesh), clip=prism)

    def seed(self, outlines, heights):
        """Take the outlines of :attr:`mesh` already sliced on this model's
        layers (:func:`layer_heights`, :func:`slice_layers`), unless sliced."""
        if self._layers is None:
            self._layers = (outlines, heights) + overhangs(outlines, self.settings)

    def layers(self):
        """(outlines, heights, overhangs, bridges), one item per layer."""
        if self._layers is None:
            s = self.settings
            _check_above_bed(self.mesh)
            z, h = layer_heights(float(self.mesh.bounds[1][2]), s)
            outlines = slice_layers(to_manifold(self.mesh), z - h / 2.0, s.resolution_mm)
            self._layers = (outlines, h) + overhangs(outlines, s)
        return self._layers


# ----------------------------------------------------------------- layers

def layer_heights(z_max, settings):
    """Layer tops and thicknesses from the bed (z = 0) up to ``z_max``.

    The first layer is ``first_layer_height_mm`` thick, the others
    ``layer_height_mm``; a layer exists while its middle is below ``z_max``.

    Returns
    -------
    z_tops : (L,) float, mm
    heights : (L,) float, mm
    """
    h0, h = settings.first_layer_height_mm, settings.layer_height_mm
    n = max(int(math.ceil((z_max - h0) / h)) + 2, 1)  # enough layers, trimmed below
    z_tops = h0 + h * np.arange(n)
    heights = np.full(n, h)
    heights[0] = h0
    keep = z_tops - heights / 2.0 < z_max
    return z_tops[keep], heights[keep]


def slice_layers(solid, z_cuts, resolution_mm):
    """Cross-sections of ``solid`` (manifold3d.Manifold) at heights ``z_cuts``
    ((L,) mm), simplified to ``resolution_mm``: a list of L CrossSections."""
    return [solid.slice(float(z)).simplify(resolution_mm) for z in z_cuts]


# ---------------------------------------------------------------- regions

def interior_regions(outlines, bottom_layers, top_layers):
    """For each layer, the area covered by the ``bottom_layers`` layers below
    it and the ``top_layers`` above it: infill there may be sparse, the rest
    of the layer is within a solid skin.  A list of L CrossSections."""
    n = len(outlines)
    empty = manifold3d.CrossSection()
    out = []
    for i in range(n):
        lo, hi = i - bottom_layers, i + top_layers
        if lo < 0 or hi >= n:
            out.append(empty)
            continue
        window = [outlines[j] for j in range(lo, hi + 1) if j != i]
        out.append(manifold3d.CrossSection.batch_boolean(window, manifold3d.OpType.Intersect)
                   if window else outlines[i])
    return out


def plan_island(island, interior, height, angle_rad, settings, bridges=()):
    """Paths of one island (one outline with its holes) of a layer, in the
    order of printing: perimeters from the innermost loop out to the
    external one, then solid infill, then sparse infill.

    Parameters
    ----------
    island : manifold3d.CrossSection
    interior : manifold3d.CrossSection
      Area of the layer covered by the layers above and below
      (:func:`interior_regions`).
    height : float, mm
    angle_rad : float
      Infill direction.
    bridges : list of (CrossSection, float)
      Bridges of this layer and their directions (rad,
      :func:`ambots.support.overhangs`): the solid infill over them (and a
      bead width into their anchors) runs that way, across the gap.

    Returns
    -------
    groups : list of list of Path
      Paths within one group may be reordered; groups keep their order.
    """
    s = settings
    w, sp = s.bead_width_mm, s.bead_spacing_mm(height)
    groups = perimeter_loops(island, w, sp, s.perimeters)[::-1]
    # the perimeters fill the band out to (w - sp)/2 + P sp; infill lines stop
    # half a bead spacing further in, minus the overlap
    clip = island.offset(-((w - sp) / 2.0 + s.perimeters * sp + sp / 2.0
                           - s.infill_overlap * w), manifold3d.JoinType.Miter)
    if clip.is_empty():
        return groups
    solid = clip - interior
    sparse = clip ^ interior
    walls = [seg for g in groups for seg in loop_segments(g)]
    walls = np.concatenate(walls) if walls else np.zeros((0, 2, 2))
    regions = []
    for span, span_angle in bridges:
        if solid.is_empty():
            break
        part = solid ^ span.offset(2.0 * w, manifold3d.JoinType.Round)
        if not part.is_empty():
            regions.append((part, sp, SOLID_INFILL, span_angle))
            solid = solid - part
    regions += [(solid, sp, SOLID_INFILL, angle_rad),
                (sparse, sp / max(s.infill_density, 1e-9), SPARSE_INFILL, angle_rad)]
    for region, spacing, feature, direction in regions:
        if region.is_empty() or (feature == SPARSE_INFILL and s.infill_density <= 0):
            continue
        segments = hatch(region.to_polygons(), direction, spacing, min_length=w)
        lines = chain_lanes(segments, infill_link_mm(feature, spacing, w), walls)
        if lines:
            groups.append([Path(feature, p, False) for p in lines])
    return groups


# ------------------------------------------------------------- perimeters

def perimeter_loops(island, bead_width, spacing, count):
    """Perimeter centre lines: inward offsets of ``island`` at ``w/2``,
    ``w/2 + sp``, ... (``count`` of them, fewer where the part is thin).

    Returns
    -------
    groups : list of list of Path
      ``groups[k]`` holds the closed loops at offset k (the outline's and
      its holes'); k = 0 is the external perimeter.
    """
    groups = []
    for k in range(count):
        ring = island.offset(-(bead_width / 2.0 + k * spacing), manifold3d.JoinType.Miter)
        loops = [p for p in ring.to_polygons() if len(p) >= 3]
        if not loops:
            break
        feature = EXTERNAL_PERIMETER if k == 0 else PERIMETER
        groups.append([Path(feature, np.asarray(p, dtype=float), True) for p in loops])
    return groups


# ----------------------------------------------------------------- infill

def hatch(polygons, angle_rad, spacing, min_length=0.0):
    """Clip parallel lines to a region (vectorised scan-line fill).

    The lines run along ``(cos a, sin a)``; line k lies at signed distance
    ``(k + 1/2) spacing`` from the origin, so layers with the same angle
    put their lines on the same grid.  Crossings of each line with the
    contours are paired even-odd (a vertex on a line counts on the edge
    that starts there going up, so the count is always even).

    Parameters
    ----------
    polygons : list of (n_i, 2) float
      Closed contours (outlines and holes), mm.
    angle_rad : float
    spacing : float, mm
    min_length : float, mm
      Shorter pieces are dropped.

    Returns
    -------
    segments : (M, 2, 2) float
      Start and end of each piece, mm, sorted by line then along the line.
    line : (M,) int
      Line index k of each piece.
    """
    polygons = [p for p in polygons if len(p) >= 3]
    if not polygons:
        return np.zeros((0, 2, 2)), np.zeros(0, dtype=int)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    pts = np.concatenate(polygons)
    sizes = np.array([len(p) for p in polygons])
    starts = np.repeat(np.cumsum(sizes) - sizes, sizes)
    nxt = starts + (np.arange(len(pts)) - starts + 1) % np.repeat(sizes, sizes)
    u = pts @ np.array([c, s])        # along the lines
    v = pts @ np.array([-s, c])       # across the lines
    ua, va, ub, vb = u, v, u[nxt], v[nxt]
    # lines k with v_k = (k + 1/2) spacing in [min(va, vb), max(va, vb))
    k0 = np.ceil(np.minimum(va, vb) / spacing - 0.5).astype(np.int64)
    k1 = np.ceil(np.maximum(va, vb) / spacing - 0.5).astype(np.int64)
    count = k1 - k0
    edge = np.repeat(np.arange(len(pts)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    k = k0[edge] + np.arange(len(edge)) - first
    t = ((k + 0.5) * spacing - va[edge]) / (vb[edge] - va[edge])
    uk = ua[edge] + t * (ub[edge] - ua[edge])
    order = np.lexsort((uk, k))
    k, uk = k[order].reshape(-1, 2)[:, 0], uk[order].reshape(-1, 2)
    keep = uk[:, 1] - uk[:, 0] > max(min_length, 1e-9)
    k, uk = k[keep], uk[keep]
    vk = (k + 0.5) * spacing
    # back to x, y: p = u (c, s) + v (-s, c)
    x = uk * c - vk[:, None] * s
    y = uk * s + vk[:, None] * c
    return np.stack([x, y], axis=-1), k


#: sparse infill lines are joined by extruded links up to this many line
#: spacings long (PrusaSlicer's connected rectilinear infill, its
#: ``infill_anchor``): at 45 deg to a wall the next line starts 1.4 spacings
#: along it, and each link saves a retraction, a travel and an unretraction
#: (the demo block: 4,330 -> 150 runs of extrusion, 9,890 -> 9,460 s by the
#: UR10 alone)
SPARSE_LINK_SPACINGS = 3.0


def infill_link_mm(feature, spacing, bead_width):
    """The longest extruded link between two infill lines (mm): solid
    infill's lines are a bead apart, joined within 2 bead widths; sparse
    infill's within :data:`SPARSE_LINK_SPACINGS` of their spacing."""
    if feature == SPARSE_INFILL:
        return max(2.0 * bead_width, SPARSE_LINK_SPACINGS * spacing)
    return 2.0 * bead_width


def loop_segments(paths):
    """The straight pieces (m, 2, 2) of closed paths (perimeter loops)."""
    out = [np.stack([p.points, np.roll(p.points, -1, axis=0)], axis=1) for p in paths if p.closed and len(p.points)]
    return out


def crossing(A, B, walls, boxes=None):
    """Which links A[i] -> B[i] ((m, 2) each, mm) cross one of ``walls``
    ((p, 2, 2) segments): a link that crosses no perimeter loop of its
    island stays inside the innermost one, i.e. inside the part.
    ``boxes``: the walls' (lo, hi) corners (:func:`wall_boxes`), if the
    caller asks about the same walls again and again.  The turn test runs
    on the pairs whose boxes overlap only."""
    m = len(A)
    hit = np.zeros(m, dtype=bool)
    if not m or not len(walls):
        return hit
    lo, hi = np.minimum(A, B), np.maximum(A, B)
    wlo, whi = wall_boxes(walls) if boxes is None else boxes
    C, D = walls[:, 0], walls[:, 1]

    def side(P, Q, R):             # sign of the turn P -> Q -> R
        return np.sign((Q[..., 0] - P[..., 0]) * (R[..., 1] - P[..., 1])
                       - (Q[..., 1] - P[..., 1]) * (R[..., 0] - P[..., 0]))

    for i in range(0, m, 256):     # bounded memory: 256 links x p walls at a time
        near = ((lo[i:i + 256, None] <= whi[None]) & (wlo[None] <= hi[i:i + 256, None])).all(axis=2)
        r, c = np.nonzero(near)
        if not len(r):
            continue
        a, b, cc, dd = A[i + r], B[i + r], C[c], D[c]
        proper = (side(a, b, cc) * side(a, b, dd) < 0) & (side(cc, dd, a) * side(cc, dd, b) < 0)
        hit[i + r[proper]] = True
    return hit


def wall_boxes(walls):
    """The corners (lo, hi), (p, 2) each, of the boxes of ``walls`` ((p, 2, 2) segments)."""
    return walls.min(axis=1), walls.max(axis=1)


def chain_lanes(hatched, link_max, walls=None):
    """Order clipped lines into zig-zag lanes and join them into polylines.

    Consecutive lines with the same number of pieces form a run; piece j of
    every line of a run is lane j.  Lanes are printed one after the other,
    each as a zig-zag (every other line reversed); a jump shorter than
    ``link_max`` between two lines is extruded unless it crosses one of
    ``walls`` ((p, 2, 2) segments: the island's perimeter loops,
    :func:`crossing`); any other starts a new polyline (the writer travels,
    retracting if it is long).

    Parameters
    ----------
    hatched : ((M, 2, 2) float, (M,) int)
      Output of :func:`hatch`.
    link_max : float, mm
    walls : (p, 2, 2) float, mm, optional

    Returns
    -------
    polylines : list of (n_i, 2) float
    """
    segments, line = hatched
    if len(segments) == 0:
        return []
    lines, first, per_line = np.unique(line, return_index=True, return_counts=True)
    slot = np.arange(len(line)) - np.repeat(first, per_line)
    new_run = np.ones(len(lines), dtype=bool)
    new_run[1:] = (np.diff(lines) != 1) | (np.diff(per_line) != 0)
    run = np.repeat(np.cumsum(new_run), per_line)
    order = np.lexsort((line, slot, run))
    flip = (line[order] % 2).astype(bool)
    seg = segments[order]
    seg[flip] = seg[flip, ::-1]
    pts = seg.reshape(-1, 2)
    gap = np.linalg.norm(seg[1:, 0] - seg[:-1, 1], axis=1)
    cut = gap > link_max
    if walls is not None and len(walls):
        short = np.flatnonzero(~cut)
        cut[short] = crossing(seg[:-1, 1][short], seg[1:, 0][short], walls)
    breaks = np.flatnonzero(cut) + 1
    return np.split(pts, 2 * breaks)


# --------------------------------------------------------------- ordering

def order_islands(islands, start_xy):
    """Print order of a layer's islands and of the paths in each.

    Islands go nearest first; within an island, groups keep their order.
    The loops of a perimeter group are taken nearest first, each starting
    at its vertex nearest the nozzle (the seam); infill polylines keep the
    order of :func:`chain_lanes`, each starting at its nearer end.

    Parameters
    ----------
    islands : list of list of list of Path (from :func:`plan_island`)
    start_xy : (2,) float, mm

    Yields
    ------
    paths : list of Path, one island at a time, ready to print
    """
    pos = np.asarray(start_xy, dtype=float)
    todo = [isl for isl in islands if isl]
    while todo:
        island = todo.pop(int(np.argmin([_nearest(isl[0][0], pos)[1] for isl in todo])))
        out = []
        for group in island:
            group = list(group)
            while group:
                j = 0
                if group[0].closed and len(group) > 1:
                    j = int(np.argmin([_nearest(p, pos)[1] for p in group]))
                path = group.pop(j)
                path = _start_at(path, _nearest(path, pos)[0])
                out.append(path)
                pos = path.points[0] if path.closed else path.points[-1]
        yield out


def _nearest(path, pos):
    """(index of the start point nearest ``pos``, its distance)."""
    if path.closed:
        d = np.einsum("ij,ij->i", path.points - pos, path.points - pos)
        i = int(np.argmin(d))
        return i, math.sqrt(d[i])
    d0 = np.hypot(*(path.points[0] - pos))
    d1 = np.hypot(*(path.points[-1] - pos))
    return (0, d0) if d0 <= d1 else (-1, d1)


def _start_at(path, i):
    if path.closed:
        return path._replace(points=np.roll(path.points, -i, axis=0)) if i else path
    return path._replace(points=path.points[::-1]) if i == -1 else path


def order_paths(paths, start_xy):
    """``paths`` (list of Path, e.g. one layer's support) in print order from
    ``start_xy`` ((2,) mm): loops nearest first, each started at its vertex
    nearest the nozzle; then the lines in their given order (the lanes of
    :func:`chain_lanes`), each from its nearer end."""
    pos = np.asarray(start_xy, dtype=float)
    loops = [p for p in paths if p.closed]
    out = []
    while loops:
        path = loops.pop(int(np.argmin([_nearest(p, pos)[1] for p in loops])))
        path = _start_at(path, _nearest(path, pos)[0])
        out.append(path)
        pos = path.points[0]
    for path in paths:
        if not path.closed:
            path = _start_at(path, _nearest(path, pos)[0])
            out.append(path)
            pos = path.points[-1]
    return out


# ----------------------------------------------------------------- G-code

class GcodeWriter:
    """PrusaSlicer-style G-code: absolute XYZ, relative E (``M83``),
    ``;LAYER_CHANGE``/``;Z:``/``;HEIGHT:`` and ``;TYPE:`` comments,
    retraction before long travels and at layer changes."""

    def __init__(self, settings, model_name="model"):
        self.s = settings
        self.xy = np.zeros(2)
        self.z = 0.0
        self.first_layer = True
        self.feature = None
        self.retracted = False
        self.filament_mm = 0.0
        self.layers = 0
        s = settings
        # the model name is a file name, which may hold a line break followed
        # by G-code: it goes in the comment escaped, printable ASCII only
        name = "".join(c if " " <= c <= "~" else ascii(c)[1:-1] for c in str(model_name))
        self.chunks = ["; generated by ambots %s (built-in slicer)\n; model: %s\n"
                       % (ambots.__version__, name)]
        self.chunks += ["; %s = %s\n" % (f.name, getattr(s, f.name))
                        for f in dataclasses.fields(s)]
        self.chunks.append("; bead width = %.3f mm, spacing = %.3f mm\n\n"
                           % (s.bead_width_mm, s.bead_spacing_mm(s.layer_height_mm)))
        self.chunks.append("G21 ; set units to millimeters\nG90 ; use absolute coordinates\n"
                           "M83 ; use relative distances for extrusion\n")
        if s.nozzle_temperature_c is not None:
            self.chunks.append("M109 S%d ; set temperature and wait for it to be reached\n"
                               % round(s.nozzle_temperature_c))
        self.record = MoveRecord()           # the G1 lines as the parser will read them
        self.record.text("".join(self.chunks))
        self.feeds = {EXTERNAL_PERIMETER: s.external_perimeter_feedrate_mm_min,
                      PERIMETER: s.perimeter_feedrate_mm_min,
                      SOLID_INFILL: s.solid_infill_feedrate_mm_min,
                      SPARSE_INFILL: s.infill_feedrate_mm_min,
                      SUPPORT: s.support_feedrate_mm_min,
                      SUPPORT_INTERFACE: s.support_feedrate_mm_min}

    def layer_change(self, z, height, first=False):
        """Start a layer whose top is at ``z`` (mm), ``height`` thick."""
        self.first_layer = first
        if self.filament_mm > 0:  # nothing to hold back before the first extrusion
            self._retract()
        self.z = float(z)
        self.layers += 1
        self.record.marker()
        self.chunks.append(";LAYER_CHANGE\n;Z:%.3f\n;HEIGHT:%.3f\n" % (z, height))
        self.record.text(self.chunks[-1])
        self._move(z=z, f=self.s.z_feedrate_mm_min)
        self.feature = None

    def _move(self, x=None, y=None, z=None, e=None, f=None):
        """One ``G1`` line with these words (X, Y, Z 3 decimals, E 5, F an
        integer), recorded as written."""
        x = None if x is None else "%.3f" % x
        y = None if y is None else "%.3f" % y
        z = None if z is None else "%.3f" % z
        e = None if e is None else "%.5f" % e
        f = None if f is None else "%d" % f
        line = "G1"
        for k, w in (("X", x), ("Y", y), ("Z", z), ("E", e), ("F", f)):
            if w is not None:
                line += " " + k + w
        self.chunks.append(line + "\n")
        self.record.move(x, y, z, e, f)

    def set_z(self, z):
        """Move the nozzle to height ``z`` (mm) within the layer (the
        support's contact layer is printed lower than the layer's top)."""
        z = float(z)
        if abs(z - self.z) > 1e-9:
            self._move(z=z, f=self.s.z_feedrate_mm_min)
            self.z = z

    def extrude(self, path, height):
        """Travel to the start of ``path`` and extrude along it."""
        pts = path.points
        if path.closed:
            pts = np.concatenate([pts, pts[:1]])
        lengths = np.hypot(*np.diff(pts, axis=0).T)
        if (lengths <= 5e-4).any():  # below the printed resolution
            pts = pts[np.concatenate([[True], lengths > 5e-4])]
            lengths = np.hypot(*np.diff(pts, axis=0).T)
        if len(lengths) == 0:
            return
        e = lengths * (self.s.bead_area_mm2(height) / self.s.filament_area_mm2)
        self._write(pts[0], path.feature, e, np.column_stack([pts[1:], e]).ravel())
        self.xy = pts[-1]

    def _write(self, start, feature, e, rows):
        """Travel to ``start``, then the moves of one path: ``e`` (n,) mm of
        filament each, ``rows`` their X, Y, E flattened (3 n)."""
        self.travel(start)
        if feature != self.feature:
            self.chunks.append(";TYPE:%s\n;WIDTH:%.3f\n" % (feature, self.s.bead_width_mm))
            self.record.text(self.chunks[-1])
            self.feature = feature
        feed = self.feeds[feature]
        if self.first_layer:
            feed = min(feed, self.s.first_layer_feedrate_mm_min)
        self.filament_mm += float(e.sum())
        # one %-format for the whole path: the per-point loop runs in C
        self._move(f=feed)
        self.chunks.append(("G1 X%.3f Y%.3f E%.5f\n" * len(e)) % tuple(rows))
        self.record.block(self.chunks[-1], len(e))

    def extrude_paths(self, paths, height, z=None):
        """:meth:`extrude` of each of ``paths`` in turn (the same text), the
        lengths, E and numbers to print of all of them computed at once (a
        layer has tens of paths: per path, numpy's cost per call was most
        of the writer's time).  ``z`` (mm): print them at this height (the
        support's contact layer, below the layer's top); None: where the
        nozzle is."""
        if z is not None and paths:
            self.set_z(z)
        if len(paths) < 2:
            for path in paths:
                self.extrude(path, height)
            return
        pts = [np.concatenate([p.points, p.points[:1]]) if p.closed else p.points for p in paths]
        sizes = np.array([len(q) for q in pts])
        ends = np.cumsum(sizes) - 1          # path k's moves are rows starts[k] .. ends[k] - 1 of P[1:] - P[:-1]
        starts = ends - sizes + 1
        P = np.concatenate(pts)
        D = P[1:] - P[:-1]
        lengths = np.hypot(D[:, 0], D[:, 1])
        tiny = np.concatenate([[0], np.cumsum(lengths <= 5e-4)])
        e_all = lengths * (self.s.bead_area_mm2(height) / self.s.filament_area_mm2)
        rows = np.column_stack([P[1:], e_all]).ravel().tolist()
        for path, a, b in zip(paths, starts.tolist(), ends.tolist()):
            if b <= a:
                continue                     # one point: nothing to print
            if tiny[b] != tiny[a]:           # moves below the printed resolution: dropped one by one
                self.extrude(path, height)
                continue
            self._write(P[a], path.feature, e_all[a:b], rows[3 * a:3 * b])
            self.xy = P[b]

    def travel(self, xy):
        """Move to ``xy`` without extruding; retract first if it is long."""
        s = self.s
        dist = float(np.hypot(*(xy - self.xy)))
        if dist > s.retract_min_travel_mm:
            self._retract()
        if dist > 1e-9:
            if self.retracted and s.z_hop_mm > 0:
                self._move(z=self.z + s.z_hop_mm, f=s.z_feedrate_mm_min)
            self._move(x=xy[0], y=xy[1], f=s.travel_feedrate_mm_min)
            if self.retracted and s.z_hop_mm > 0:
                self._move(z=self.z, f=s.z_feedrate_mm_min)
        self.xy = np.asarray(xy, dtype=float)
        if self.retracted:
            self._move(e=s.retract_length_mm, f=s.retract_feedrate_mm_min)
            self.retracted = False

    def _retract(self):
        if not self.retracted and self.s.retract_length_mm > 0:
            self._move(e=-self.s.retract_length_mm, f=self.s.retract_feedrate_mm_min)
            self.retracted = True

    def finish(self):
        """The whole G-code text, with PrusaSlicer's filament summary."""
        self._retract()
        if self.s.nozzle_temperature_c is not None:
            self.chunks.append("M104 S0 ; turn off temperature\n")
            self.record.text(self.chunks[-1])
        volume = self.filament_mm * self.s.filament_area_mm2
        self.chunks.append("\n; total layers count = %d\n; filament used [mm] = %.2f\n"
                           "; filament used [cm3] = %.2f\n"
                           % (self.layers, self.filament_mm, volume / 1000.0))
        self.record.text(self.chunks[-1])
        text = "".join(self.chunks)
        return SlicedText(text, self.record.layers(text))


# ============================================================ prusa-slicer

class PrusaSlicer:
    """The ``prusa-slicer`` command line, run with an argument list (never a
    shell string).

    PrusaSlicer splits some path options at ``;``, so it never sees the
    user's file names: it runs in a private temporary directory on copies
    named ``config.ini`` and ``model.stl`` and writes ``model.gcode``, which
    is then moved where it was asked.  Any file name works.

    The model stays where it is (``--dont-arrange``, ``--no-ensure-on-bed``),
    so its G-code is in the same frame as the built-in back end's.  Skirt
    and brim are disabled (the built-in slicer prints neither; around a
    piece of a shared print they would hit the neighbours).  The fields of
    :class:`SliceSettings` override the ``.ini`` (``apply_settings=True``);
    everything else (start G-code, temperatures...) comes from the ``.ini``.
    """

    name = "prusa"
    #: names of the files inside the private directory
    INI, STL, GCODE = "config.ini", "model.stl", "model.gcode"

    def __init__(self, settings=None, ini_path=None, executable="prusa-slicer",
                 timeout_s=600.0, apply_settings=True, extra_args=()):
        self.settings = settings or SliceSettings()
        self.ini_path = os.fspath(ini_path) if ini_path is not None else DEFAULT_PRUSA_INI
        self.executable = executable
        self.timeout_s = timeout_s
        self.apply_settings = apply_settings
        self.extra_args = [str(a) for a in extra_args]

    def slice(self, mesh):
        """G-code text (str) for ``mesh`` (trimesh.Trimesh, mm, on the bed)."""
        _check_above_bed(mesh)
        with tempfile.TemporaryDirectory(prefix="ambots-prusa-") as tmp:
            mesh.export(os.path.join(tmp, self.STL))
            self._run(tmp, source_name(mesh))
            with open(os.path.join(tmp, self.GCODE)) as f:
                return f.read()

    def slice_file(self, stl_path, gcode_path):
        """Slice the STL file ``stl_path`` into the file ``gcode_path``."""
        stl_path, gcode_path = os.fspath(stl_path), os.fspath(gcode_path)
        if not os.path.isfile(stl_path):
            raise SlicerError("%s: no such file" % stl_path)
        with tempfile.TemporaryDirectory(prefix="ambots-prusa-") as tmp:
            shutil.copyfile(stl_path, os.path.join(tmp, self.STL))
            self._run(tmp, os.path.basename(stl_path))
            shutil.move(os.path.join(tmp, self.GCODE), gcode_path)

    def command(self):
        """The argument list, run in the private directory."""
        cmd = [self.executable, "--loglevel", "1", "--export-gcode", "--load", self.INI,
               "--dont-arrange", "--no-ensure-on-bed", "--skirts", "0", "--brim-width", "0"]
        if self.apply_settings:
            cmd += self.settings_args()
        return cmd + self.extra_args + ["--output", self.GCODE, self.STL]

    def settings_args(self):
        """PrusaSlicer options equivalent to :attr:`settings` (speeds in mm/s)."""
        s = self.settings
        w = "%g" % s.bead_width_mm
        args = {
            "layer-height": s.layer_height_mm, "first-layer-height": s.first_layer_height_mm,
            "nozzle-diameter": s.nozzle_diameter_mm, "filament-diameter": s.filament_diameter_mm,
            "perimeters": s.perimeters, "top-solid-layers": s.top_solid_layers,
            "bottom-solid-layers": s.bottom_solid_layers, "top-solid-min-thickness": 0,
            "bottom-solid-min-thickness": 0, "fill-density": "%g%%" % (100 * s.infill_density),
            "fill-pattern": "rectilinear", "fill-angle": s.infill_angle_deg,
            "infill-overlap": "%g%%" % (100 * s.infill_overlap),
            "perimeter-speed": s.perimeter_feedrate_mm_min / 60.0,
            "external-perimeter-speed": s.external_perimeter_feedrate_mm_min / 60.0,
            "infill-speed": s.infill_feedrate_mm_min / 60.0,
            "solid-infill-speed": s.solid_infill_feedrate_mm_min / 60.0,
            "top-solid-infill-speed": s.solid_infill_feedrate_mm_min / 60.0,
            "first-layer-speed": s.first_layer_feedrate_mm_min / 60.0,
            "travel-speed": s.travel_feedrate_mm_min / 60.0,
            "retract-length": s.retract_length_mm,
            "retract-speed": s.retract_feedrate_mm_min / 60.0,
            "retract-before-travel": s.retract_min_travel_mm, "retract-lift": s.z_hop_mm,
        }
        for key in ("extrusion-width", "first-layer-extrusion-width",
                    "perimeter-extrusion-width", "external-perimeter-extrusion-width",
                    "infill-extrusion-width", "solid-infill-extrusion-width",
                    "top-infill-extrusion-width"):
            args[key] = w
        if s.nozzle_temperature_c is not None:
            args["temperature"] = args["first-layer-temperature"] = round(s.nozzle_temperature_c)
        out = ["--use-relative-e-distances"]
        if s.support:
            # PrusaSlicer's threshold is the slope from the horizontal plane, ours from vertical
            out += ["--support-material", "--support-material-auto"]
            args.update({"support-material-threshold": 90.0 - s.support_angle_deg,
                         "support-material-spacing": s.support_spacing_mm,
                         "support-material-interface-layers": s.support_interface_layers,
                         "support-material-contact-distance": s.support_z_gap_mm,
                         "support-material-xy-spacing": s.support_xy_gap_mm,
                         "support-material-speed": s.support_feedrate_mm_min / 60.0,
                         "support-material-interface-speed": s.support_feedrate_mm_min / 60.0,
                         "support-material-extrusion-width": w})
        else:
            out += ["--no-support-material"]
        for key, value in args.items():
            out += ["--" + key, value if isinstance(value, str) else "%g" % value]
        return out

    def _run(self, tmp, name):
        """Run prusa-slicer in ``tmp`` (holding model.stl); raise SlicerError
        with the tail of its output when it fails."""
        if shutil.which(self.executable) is None:
            raise SlicerError("%s: %r not found; install PrusaSlicer (apt install "
                              "prusa-slicer) or use the builtin back end" % (name, self.executable))
        if not os.path.isfile(self.ini_path):
            raise SlicerError("%s: PrusaSlicer config %s does not exist" % (name, self.ini_path))
        shutil.copyfile(self.ini_path, os.path.join(tmp, self.INI))
        try:
            proc = subprocess.run(self.command(), cwd=tmp, capture_output=True, text=True,
                                  timeout=self.timeout_s, check=False)
        except subprocess.TimeoutExpired:
            raise SlicerError("%s: prusa-slicer did not finish within %g s"
                              % (name, self.timeout_s)) from None
        if proc.returncode != 0 or not os.path.isfile(os.path.join(tmp, self.GCODE)):
            lines = [ln for ln in (proc.stderr + proc.stdout).splitlines()
                     if ln.strip() and "[trace]" not in ln]
            tail = "\n".join(lines[-10:]).replace(self.INI, self.ini_path).replace(self.STL, name)
            raise SlicerError("%s: prusa-slicer failed (exit status %d):\n%s"
                              % (name, proc.returncode, tail))


#: back ends by name, for :func:`slice_mesh` and the command line
BACKENDS = {BuiltinSlicer.name: BuiltinSlicer, PrusaSlicer.name: PrusaSlicer}


# ============================================================ which back end

#: what ``auto`` means: the ``prusa`` back end where this program is on PATH, else ``builtin``
PRUSA_EXECUTABLE = "prusa-slicer"
_VERSION_RE = re.compile(r"PrusaSlicer-(\S+)")
_versions = {}          # (path, mtime) -> version, so that a menu asks once per binary


def prusa_version(path):
    """The version of the PrusaSlicer at ``path`` as the first line of its
    ``--help`` gives it (``PrusaSlicer-2.5.0+UNKNOWN based on Slic3r``:
    ``"2.5.0+UNKNOWN"``), or ``"version unknown"``."""
    try:
        key = (path, os.stat(path).st_mtime_ns)
    except OSError:
        return "version unknown"
    if key not in _versions:
        try:
            proc = subprocess.run([path, "--help"], capture_output=True, text=True, timeout=30, check=False)
            m = _VERSION_RE.search(proc.stdout + proc.stderr)
            _versions[key] = m.group(1) if m else "version unknown"
        except (OSError, subprocess.SubprocessError):
            _versions[key] = "version unknown"
    return _versions[key]


class SlicerChoice(NamedTuple):
    """The back end a job will use and why (:func:`choose_backend`)."""
    backend: str        #: a key of :data:`BACKENDS`
    description: str    #: the slicer in words: "PrusaSlicer 2.5.0 (/usr/bin/prusa-slicer)" or "built-in slicer"
    reason: str         #: why this one, e.g. "--slicer auto: prusa-slicer is installed"


def choose_backend(requested="auto", executable=PRUSA_EXECUTABLE):
    """The back end for ``requested``: ``"builtin"`` or ``"prusa"`` as
    asked, or ``"auto"``: ``prusa`` when ``executable`` is found on PATH
    (:func:`shutil.which`, the lookup the prusa back end itself makes), else
    ``builtin``.  An explicit ``"prusa"`` without the executable is a
    :class:`SlicerError` (never a silent change of slicer)."""
    path = shutil.which(executable) if requested in ("auto", PrusaSlicer.name) else None
    if requested == "auto":
        if path is None:
            return SlicerChoice(BuiltinSlicer.name, "built-in slicer",
                                "--slicer auto: %s not found on PATH" % executable)
        return SlicerChoice(PrusaSlicer.name, "PrusaSlicer %s (%s)" % (prusa_version(path), path),
                            "--slicer auto: %s is installed" % executable)
    if requested == BuiltinSlicer.name:
        return SlicerChoice(BuiltinSlicer.name, "built-in slicer", "--slicer builtin")
    if requested == PrusaSlicer.name:
        if path is None:
            raise SlicerError("--slicer prusa: %r not found; install PrusaSlicer (apt install prusa-slicer) "
                              "or use --slicer builtin or auto" % executable)
        return SlicerChoice(PrusaSlicer.name, "PrusaSlicer %s (%s)" % (prusa_version(path), path),
                            "--slicer prusa")
    raise SlicerError("unknown slicer %r; available: auto, %s" % (requested, ", ".join(sorted(BACKENDS))))
