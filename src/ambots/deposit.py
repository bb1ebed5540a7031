"""Deposited bead geometry: what the arms have extruded, per arm.

A bead is one extruding straight segment of the nozzle path, laid as an
oriented box: ``length`` along the segment, ``width = area / height``
across it (horizontal), ``height`` (the layer height) below it.  The box's
top face contains the nozzle path (the nozzle tip is at the top of the bead
it lays) and the box extends ``height`` down from there (perpendicular to
the path, in its vertical plane, for a sloped bead), so a bead's volume
is exactly ``length x area``.  Consecutive beads overlap at their joints and
leave notches at corners, like the real beads roughly do; no rounding.

API (world frame, metres):

* :class:`Deposit` -- ``add(arm, starts, ends, area_m2, height_m)``;
  ``arms``; ``segments(arm)`` -> :class:`Beads`; ``volume_m3(arm=None)``,
  ``volume_mm3(arm=None)`` (analytic); ``bounds()`` -> (2, 3) or None;
  ``to_mesh(colours=None)`` -> one :class:`trimesh.Trimesh`; ``export(path,
  colours=None, scale=1.0)`` (PLY or STL by extension).
* :func:`bead_boxes` -- the vectorised box corners of many beads.
* :func:`bead_area_m2` -- a bead's cross-section from the filament pushed;
  :func:`deposit_of_beads` -- the one deposit builder: the beads an arm laid
  (the offline runners' or the rows the firmware nodes publish) -> a
  :class:`Deposit`, used by ``plan`` and by the live capture alike.

Mesh construction is vectorised (no Python loop per bead): 8 vertices and
12 triangles per bead, outward-facing, beads not welded together, so every
bead is a closed box and the mesh volume is the sum of the bead volumes.
"""
import os
from typing import NamedTuple

import numpy as np

__all__ = ["Beads", "Deposit", "bead_boxes", "BOX_FACES", "FILAMENT_AREA_MM2", "bead_area_m2", "deposit_of_beads"]

#: cross-section of 1.75 mm filament, mm^2
FILAMENT_AREA_MM2 = np.pi * (1.75 / 2) ** 2


def bead_area_m2(p0, p1, e_mm):
    """Cross-section (K,) m^2 of beads from ``p0`` to ``p1`` (K, 3) m laid with
    ``e_mm`` (K,) mm of filament: the filament's volume over the length (0
    for a bead of no length)."""
    L = np.linalg.norm(np.asarray(p1, float) - np.asarray(p0, float), axis=1)
    return np.where(L > 0, np.asarray(e_mm, float) * FILAMENT_AREA_MM2 * 1e-9 / np.maximum(L, 1e-12), 0.0)


def deposit_of_beads(by_arm, height_m):
    """The one deposit builder: ``by_arm`` {arm name: (p0 (K, 3), p1 (K, 3),
    e_mm (K,))} (world frame m; mm of filament) -> :class:`Deposit`, beads
    of layer height ``height_m``; beads with no length or no filament are
    left out."""
    dep = Deposit()
    for name, (p0, p1, e_mm) in by_arm.items():
        p0, p1 = np.asarray(p0, float).reshape(-1, 3), np.asarray(p1, float).reshape(-1, 3)
        area = bead_area_m2(p0, p1, e_mm)
        keep = area > 0
        if keep.any():
            dep.add(name, p0[keep], p1[keep], area[keep], height_m)
    return dep

#: triangles of one box whose corners are numbered ``4 * i + 2 * j + k`` for
#: the corner at (i, j, k) in {0, 1}^3 of a right-handed frame (outward normals)
BOX_FACES = np.array([[1, 3, 0], [4, 1, 0], [0, 3, 2], [2, 4, 0], [1, 7, 3], [5, 1, 4],
                      [5, 7, 1], [3, 7, 2], [6, 4, 2], [2, 7, 6], [6, 5, 4], [7, 5, 6]])

#: vertex colour of arms missing from ``colours`` (RGBA, 0..1)
DEFAULT_COLOUR = (0.7, 0.7, 0.7, 1.0)


class Beads(NamedTuple):
    """Beads of one arm: ``starts``, ``ends`` (K, 3) m, ``area`` (K,) m^2
    (cross-section), ``height`` (K,) m (layer height)."""
    starts: np.ndarray
    ends: np.ndarray
    area: np.ndarray
    height: np.ndarray

    @property
    def lengths(self):
        """(K,) segment lengths, m."""
        return np.linalg.norm(self.ends - self.starts, axis=1)


def _per_bead(value, k, what):
    v = np.asarray(value, dtype=float)
    if v.ndim == 0:
        v = np.full(k, float(v))
    if v.shape != (k,):
        raise ValueError("%s: expected a scalar or %d values, got shape %s" % (what, k, v.shape))
    if not np.all(np.isfinite(v) & (v > 0)):
        raise ValueError("%s must be finite and > 0" % what)
    return v


def _points(value, what):
    p = np.asarray(value, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError("%s: expected shape (K, 3), got %s" % (what, p.shape))
    if not np.all(np.isfinite(p)):
        raise ValueError("%s: values must be finite" % what)
    return p


def _frames(d):
    """Unit frames (u along, w across, v up) of directions d (K, 3), with
    u x w = v (right-handed); w horizontal, v with z >= 0.  Vertical beads
    (no horizontal direction) get w = y."""
    L = np.linalg.norm(d, axis=1, keepdims=True)
    u = d / np.where(L > 0, L, 1.0)
    w = np.stack([-u[:, 1], u[:, 0], np.zeros(len(u))], axis=1)           # z x u
    n = np.linalg.norm(w, axis=1, keepdims=True)
    w = np.where(n > 1e-9, w / np.where(n > 1e-9, n, 1.0), [[0.0, 1.0, 0.0]])
    return u, w, np.cross(u, w)


def bead_boxes(starts, ends, area, height):
    """Corners (K, 8, 3) of the boxes of K beads (see the module docstring),
    corner ``4 i + 2 j + k`` at start/end (i), right/left (j), bottom/top (k),
    matching :data:`BOX_FACES`.  Zero-length beads give flat boxes."""
    d = ends - starts
    L = np.linalg.norm(d, axis=1)
    u, w, v = _frames(d)
    half_w = (area / height / 2)[:, None]
    i = np.array([0, 0, 0, 0, 1, 1, 1, 1], dtype=float)
    j = np.array([0, 0, 1, 1, 0, 0, 1, 1], dtype=float) * 2 - 1
    k = np.array([0, 1, 0, 1, 0, 1, 0, 1], dtype=float) - 1
    return (starts[:, None, :]
            + (i[None, :, None] * L[:, None, None]) * u[:, None, :]
            + (j[None, :, None] * half_w[:, :, None]) * w[:, None, :]
            + (k[None, :, None] * height[:, None, None]) * v[:, None, :])


def _rgba_bytes(colour, arm):
    c = np.asarray(colour, dtype=float)
    if c.shape not in ((3,), (4,)) or not np.all((c >= 0) & (c <= 1)):
        raise ValueError("colour of %r: expected RGB(A) values in 0..1, got %r" % (arm, colour))
    return np.round(np.append(c, 1.0)[:4] * 255).astype(np.uint8)


class Deposit:
    """Beads extruded so far, per arm, in the world frame (m)."""

    def __init__(self):
        self._chunks = {}            # arm -> list of Beads
        self._cache = {}             # arm -> concatenated Beads

    @property
    def arms(self):
        """Arm names in the order they first added beads."""
        return list(self._chunks)

    def __len__(self):
        return sum(len(b.starts) for arm in self._chunks for b in self._chunks[arm])

    def add(self, arm, starts, ends, area_m2, height_m):
        """Add K beads of ``arm``: ``starts``, ``ends`` (K, 3) m, world frame
        (the nozzle tip path: the beads' top edges); ``area_m2`` cross-section
        (K,) or scalar, m^2; ``height_m`` layer height (K,) or scalar, m."""
        s, e = _points(starts, "starts"), _points(ends, "ends")
        if s.shape != e.shape:
            raise ValueError("starts and ends differ in shape: %s and %s" % (s.shape, e.shape))
        k = len(s)
        beads = Beads(s, e, _per_bead(area_m2, k, "area_m2"), _per_bead(height_m, k, "height_m"))
        self._chunks.setdefault(str(arm), []).append(beads)
        self._cache.pop(str(arm), None)

    def segments(self, arm):
        """:class:`Beads` of one arm (empty arrays for an arm with none)."""
        if arm not in self._chunks:
            return Beads(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
        if arm not in self._cache:
            chunks = self._chunks[arm]
            self._cache[arm] = Beads(*(np.concatenate(parts) for parts in zip(*chunks)))
        return self._cache[arm]

    def _all(self, arm=None):
        names = self.arms if arm is None else [arm]
        return [(a, self.segments(a)) for a in names]

    def volume_m3(self, arm=None):
        """Deposited volume (m^3) of one arm or all: sum of length x area."""
        return float(sum(np.dot(b.lengths, b.area) for _, b in self._all(arm)))

    def volume_mm3(self, arm=None):
        """:meth:`volume_m3` in mm^3."""
        return self.volume_m3(arm) * 1e9

    def boxes(self, arm=None):
        """Box corners (K, 8, 3) of one arm's beads or all arms' (in :attr:`arms` order)."""
        parts = [bead_boxes(*b) for _, b in self._all(arm)]
        return np.concatenate(parts) if parts else np.zeros((0, 8, 3))

    def bounds(self, arm=None):
        """(2, 3) [min, max] corners of the beads' boxes, m; None when empty."""
        corners = self.boxes(arm).reshape(-1, 3)
        if not len(corners):
            return None
        return np.stack([corners.min(axis=0), corners.max(axis=0)])

    def to_mesh(self, colours=None):
        """All beads as one :class:`trimesh.Trimesh` (m, world frame), 8
        vertices and 12 faces per bead, unwelded.  ``colours``: optional
        ``{arm: (r, g, b[, a])}`` in 0..1 (as the profiles' filament colour),
        set as vertex colours (arms not named: grey).  Empty deposit: an empty
        mesh."""
        import trimesh
        named = self._all()
        corners = self.boxes()
        K = len(corners)
        faces = (BOX_FACES[None] + 8 * np.arange(K)[:, None, None]).reshape(-1, 3)
        kw = {}
        if colours is not None and K:
            counts = [len(b.starts) for _, b in named]
            rgba = np.stack([_rgba_bytes(colours.get(a, DEFAULT_COLOUR), a) for a, _ in named])
            kw["vertex_colors"] = np.repeat(rgba, np.array(counts) * 8, axis=0)
        return trimesh.Trimesh(corners.reshape(-1, 3), faces, process=False, **kw)

    def export(self, path, colours=None, scale=1.0):
        """Write the beads' mesh to ``path``: ``.ply`` (binary, with vertex
        colours if ``colours`` is given) or ``.stl`` (binary).  ``scale``
        multiplies the coordinates (1000.0 writes millimetres, which slicers
        and most viewers assume).  Returns the path."""
        ext = os.path.splitext(str(path))[1].lower()
        if ext not in (".ply", ".stl"):
            raise ValueError("%s: export writes .ply or .stl, not %r" % (path, ext or "no extension"))
        if not len(self):
            raise ValueError("%s: nothing deposited, no mesh to write" % path)
        mesh = self.to_mesh(colours)
        if scale != 1.0:
            mesh.vertices = mesh.vertices * float(scale)
        mesh.export(str(path), file_type=ext[1:])
        return path
