"""Model input: read a mesh file, repair what can be repaired, refuse the rest.

Every model is a :class:`trimesh.Trimesh` in **millimetres** (STL, OBJ, PLY and
3MF carry no reliable unit; use ``scale`` to convert, e.g. ``scale=25.4`` for
inches).  The slicer and the G-code share this frame, which is why this module
works in mm rather than in the metres used elsewhere in the package (see
:mod:`ambots.units`).

The pipeline of :func:`load_model` is::

    check the file -> read -> check the numbers -> scale -> weld -> repair -> validate

and every refusal is a :class:`~ambots.errors.MeshError` whose message starts
with the file name and names the defect ("223 open edges", "zero volume"...),
so a user can fix the input without reading a traceback.
"""
import logging
import os
import struct
import weakref

import manifold3d
import numpy as np
import trimesh

from ambots.errors import MeshError
from ambots.gcode import MAX_ABS_MM

log = logging.getLogger(__name__)

#: file extensions :func:`load_model` reads (lower case, without the dot)
SUPPORTED_FORMATS = ("stl", "obj", "ply", "3mf")

#: default refusal limit on the number of triangles of a model
DEFAULT_MAX_TRIANGLES = 5_000_000

#: key of ``Trimesh.metadata`` holding the name used in messages
SOURCE_KEY = "ambots_source"
#: key of ``Trimesh.metadata`` holding the list of repairs made on load
REPAIRS_KEY = "ambots_repairs"
#: key of ``Trimesh.metadata`` holding the :class:`ambots.repair.RepairReport`
REPORT_KEY = "ambots_repair"


# ---------------------------------------------------------------- loading

def load_model(path, scale=1.0, max_triangles=DEFAULT_MAX_TRIANGLES, repair=True, crossings=True):
    """Read a model file and return a closed, consistently oriented mesh.

    Parameters
    ----------
    path : str or os.PathLike
      An ``.stl`` (ASCII or binary), ``.obj``, ``.ply`` or ``.3mf`` file.
    scale : float
      Factor applied to the vertices; the result is in millimetres.
    max_triangles : int
      Files with more triangles are refused (the message gives the count).
    repair : bool
      Drop degenerate and duplicate triangles, close holes that are
      small against the model (:mod:`ambots.repair`), fix
      winding and normals, and merge overlapping shells.  With ``False``
      the mesh is only welded (shared vertices merged) and validated.
    crossings : bool
      With ``False`` the search for a surface crossing itself (its repair,
      its refusal) is left out: the caller runs :func:`crosses_itself` on
      the mesh aside and loads the file again with it when that finds a
      crossing (the job does: :func:`ambots.job.run_job`).

    Returns
    -------
    mesh : trimesh.Trimesh
      Watertight, outward-oriented, positive volume, in mm.
      ``mesh.metadata['ambots_source']`` is the file name and
      ``mesh.metadata['ambots_repairs']`` lists the repairs made (strings),
      ``mesh.metadata['ambots_repair']`` is the
      :class:`ambots.repair.RepairReport` (with ``repair``).

    Raises
    ------
    MeshError
      The file is missing, empty, of an unknown format, not a mesh, too
      large, has non-finite coordinates, or is still not a closed volume
      after repair.
    """
    path = os.fspath(path)
    name = os.path.basename(path) or path
    if not (np.isfinite(scale) and scale > 0):
        raise MeshError("%s: scale must be a positive number, got %r" % (name, scale))
    ext = _check_file(path, name)
    if ext == "stl":
        _check_binary_stl_count(path, name, max_triangles)
    mesh = _read(path, name, ext)
    check_numbers(mesh, name, max_triangles, scale)
    if scale != 1.0:
        mesh.apply_scale(float(scale))
    mesh.metadata[SOURCE_KEY] = name
    mesh.metadata[REPAIRS_KEY] = []
    # weld: STL stores every triangle's corners apart, OBJ splits vertices
    # by normal and texture; a closed surface needs shared vertices (the
    # repair starts with it: once is enough, 0.2 s on 300,000 triangles)
    if not repair:
        weld(mesh)
    # trimesh divides by the volume (centre of mass) in several places:
    # a flat mesh must end up as a message, not as a RuntimeWarning
    with np.errstate(divide="ignore", invalid="ignore"):
        if repair:
            mesh = repair_mesh(mesh, crossings)
        validate_mesh(mesh, crossings=crossings)
    for note in mesh.metadata[REPAIRS_KEY]:
        log.info("%s: repaired: %s", name, note)
    return mesh


def _check_file(path, name):
    """Refuse a missing, empty or unknown-format file; return its extension."""
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    if ext not in SUPPORTED_FORMATS:
        raise MeshError("%s: unknown model format %r; supported: %s" % (
            name, "." + ext if ext else "(no extension)",
            ", ".join("." + e for e in SUPPORTED_FORMATS)))
    if os.path.isdir(path):
        raise MeshError("%s: is a folder, not a model file" % path)
    if not os.path.isfile(path):
        raise MeshError("%s: no such file" % path)
    if os.path.getsize(path) == 0:
        raise MeshError("%s: file is empty" % name)
    return ext


def _check_binary_stl_count(path, name, max_triangles):
    """Refuse a binary STL announcing too many triangles, or more than the
    file holds, before reading it (a forged count must not cost time or memory).

    A binary STL is an 80-byte header, a uint32 triangle count and 50 bytes
    per triangle; a file whose size matches that layout is binary.  A file
    that does not match it and does not look like ASCII STL (``solid`` then
    text) is refused: truncated, or not an STL file at all."""
    size = os.path.getsize(path)
    if size < 84:
        return
    try:
        with open(path, "rb") as f:
            head = f.read(1024)
    except OSError as exc:
        raise MeshError("%s: cannot read: %s" % (name, exc.strerror or exc)) from None
    (count,) = struct.unpack("<I", head[80:84])
    binary = size == 84 + 50 * count
    if binary and count > max_triangles:
        raise MeshError("%s: %s triangles, more than the limit of %s" % (
            name, format(count, ","), format(max_triangles, ",")))
    if not binary and not (head.lstrip()[:5].lower() == b"solid" and b"\0" not in head):
        raise MeshError("%s: not a readable STL file: not ASCII STL, and as binary STL its "
                        "header announces %s triangles (%s bytes) but the file has %s bytes"
                        % (name, format(count, ","), format(84 + 50 * count, ","),
                           format(size, ",")))


#: one triangle of a binary STL: normal, three corners (float32), attribute bytes
_STL_TRIANGLE = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])


def _read_binary_stl(path):
    """A binary STL (its size is 84 bytes + 50 per triangle announced) as a
    Trimesh, unprocessed: each triangle's three corners its own vertices, in
    the file's order, as trimesh's loader gives them (float64), read in one
    numpy call (0.04 s against trimesh's 0.2 s for 327,680 triangles); None
    for any other file (ASCII STL: trimesh reads it)."""
    with open(path, "rb") as f:
        data = f.read()
    if len(data) < 84:
        return None
    (count,) = struct.unpack("<I", data[80:84])
    if len(data) != 84 + 50 * count:
        return None
    corners = np.frombuffer(data, _STL_TRIANGLE, count, 84)["corners"].reshape(-1, 3).astype(np.float64)
    return trimesh.Trimesh(corners, np.arange(len(corners), dtype=np.int64).reshape(-1, 3), process=False)


def _read(path, name, ext):
    """Read any supported file into one Trimesh, unprocessed."""
    try:
        # trimesh raises whatever its format parsers raise (ValueError,
        # BadZipFile, KeyError, struct.error...): all mean "not a mesh"
        mesh = _read_binary_stl(path) if ext == "stl" else None
        if mesh is None:
            mesh = trimesh.load(path, file_type=ext, force="mesh", process=False)
    except OSError as exc:
        raise MeshError("%s: cannot read: %s" % (name, exc.strerror or exc)) from None
    except Exception as exc:  # noqa: BLE001 -- boundary to third-party parsers
        raise MeshError("%s: not a readable %s file (%s: %s)" % (
            name, ext.upper(), type(exc).__name__, exc)) from None
    if isinstance(mesh, trimesh.Scene):  # force='mesh' gives a Scene when empty
        mesh = trimesh.Trimesh()
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError("%s: contains no triangles: not a valid %s file" % (name, ext.upper()))
    return mesh


def check_numbers(mesh, name, max_triangles=DEFAULT_MAX_TRIANGLES, scale=1.0):
    """Refuse too many triangles, non-finite vertices, coordinates beyond
    :data:`ambots.gcode.MAX_ABS_MM` once multiplied by ``scale`` (no G-code
    could reach them; the geometry code would overflow) and bad indices."""
    n = len(mesh.faces)
    if n > max_triangles:
        raise MeshError("%s: %s triangles, more than the limit of %s" % (
            name, format(n, ","), format(max_triangles, ",")))
    vertices = np.asarray(mesh.vertices)
    # the extremes first (one pass each); vertex by vertex only to word a refusal
    low, high = (vertices.min(), vertices.max()) if vertices.size else (0.0, 0.0)
    if not (np.isfinite(low) and np.isfinite(high)):
        bad = ~np.isfinite(vertices).all(axis=1)
        raise MeshError("%s: %d vertices have NaN or infinite coordinates (first: vertex %d)"
                        % (name, bad.sum(), np.flatnonzero(bad)[0]))
    if max(-low, high) * scale > MAX_ABS_MM:
        bad = (np.abs(vertices) * scale > MAX_ABS_MM).any(axis=1)
        raise MeshError("%s: %d vertices lie beyond +-%g mm (first: vertex %d); wrong unit "
                        "or broken file" % (name, bad.sum(), MAX_ABS_MM, np.flatnonzero(bad)[0]))
    if len(mesh.vertices) == 0 or mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        raise MeshError("%s: triangles refer to vertices that do not exist" % name)


# ----------------------------------------------------------------- repair

def repair_mesh(mesh, crossings=True):
    """Repair what can be repaired and return the mesh (``mesh`` itself or
    a new one).

    Steps: merge coincident vertices (no note: routine); drop degenerate and
    duplicate triangles; close the holes with MeshFix when the defect is
    small against the model (:func:`ambots.repair.close_holes`: the rule,
    and the refusal with the figures when it is broken); make the winding
    consistent and the normals point outward; merge shells that overlap
    each other (a self-intersection left by exporting several parts as one
    mesh); repair a surface that crosses itself when the defect is small
    (:func:`ambots.selfcross.repair_crossings`: the rule, and the refusal with
    the figure that failed; not with ``crossings`` False: :func:`load_model`).
    Each change is appended to ``mesh.metadata['ambots_repairs']``;
    ``mesh.metadata['ambots_repair']`` is the
    :class:`ambots.repair.RepairReport`.
    """
    from ambots.repair import RepairReport, close_holes
    notes = mesh.metadata.setdefault(REPAIRS_KEY, [])
    report = mesh.metadata[REPORT_KEY] = RepairReport()
    n_face = report.faces_before = len(mesh.faces)
    weld(mesh)                           # done by load_model too
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) < n_face:
        notes.append("removed %d degenerate or duplicate triangles" % (n_face - len(mesh.faces)))
    n_open = report.open_edges_before = open_edge_count(mesh)
    n_nonman = nonmanifold_edge_count(mesh) if n_open else 0
    if n_open and n_nonman:
        raise MeshError("%s: not a closed volume: %d open edges and %d non-manifold edges (shared by more "
                        "than two triangles): holes are closed only in a manifold mesh"
                        % (source_name(mesh), n_open, n_nonman))
    if n_open and len(mesh.faces):
        trimesh.repair.fix_winding(mesh)     # the winding number needs one orientation
        closed = close_holes(mesh, source_name(mesh), report)
        closed.metadata.update(mesh.metadata)
        mesh = closed
        if report.holes_closed:
            notes.append("closed %d hole%s with %d triangle%s (%.1f mm^2 of fill); volume %s -> %.1f mm^3"
                         % (report.holes_closed, "" if report.holes_closed == 1 else "s", report.faces_added,
                            "" if report.faces_added == 1 else "s",
                            report.fill_area_mm2, "?" if report.volume_before_mm3 is None
                            else "%.1f" % report.volume_before_mm3,
                            report.volume_after_mm3 if report.volume_after_mm3 is not None else mesh.volume))
    n_flip = _fix_orientation(mesh)
    if n_flip:
        notes.append("flipped %d triangles to make the normals point outward" % n_flip)
    mesh = _merge_overlapping_shells(mesh)
    if crossings:
        mesh = _repair_crossings(mesh, report)
    report.faces_after = len(mesh.faces)
    report.open_edges_after = open_edge_count(mesh)
    return mesh


#: key of ``Trimesh.metadata``: the hash of the mesh found not to cross itself
#: by :func:`repair_mesh` (:func:`check_self_intersection` does not look again)
UNCROSSED_KEY = "ambots_uncrossed"


def weld(mesh):
    """Merge coincident vertices of ``mesh`` in place: what
    ``mesh.merge_vertices(merge_tex=True, merge_norm=True)`` does (the same
    vertices, in the same order, the same triangles), 2.5x faster on a mesh
    read from STL: the rows of integer coordinates are grouped by sorting one
    64-bit hash of each (every group checked to hold equal rows; trimesh's
    own when two rows share a hash), not by sorting 24-byte rows."""
    if len(mesh.vertices) == 0:
        return
    if len(mesh.faces) > 0:
        referenced = np.zeros(len(mesh.vertices), dtype=bool)
        referenced[mesh.faces] = True
    else:
        referenced = np.ones(len(mesh.vertices), dtype=bool)
    digits = trimesh.util.decimal_to_digits(trimesh.tol.merge)
    every = bool(referenced.all())
    scaled = np.multiply(np.asarray(mesh.vertices) if every else mesh.vertices[referenced], 10 ** digits)
    rows = np.round(scaled, out=scaled).astype(np.int64)       # fewer new arrays: 0.1 s of page faults
    with np.errstate(over="ignore"):
        u64 = rows.view(np.uint64)
        code = u64[:, 0] * np.uint64(0x9E3779B97F4A7C15)          # one column after the other, mixed
        for column, factor in ((1, 0xC2B2AE3D27D4EB4F), (2, 0x165667B19E3779F9)):
            code ^= code >> np.uint64(31)
            code += u64[:, column]
            code *= np.uint64(factor)
        code ^= code >> np.uint64(29)
    perm = np.argsort(code)
    code_s, rows_s = code[perm], np.take(rows, perm, axis=0)
    new = np.concatenate([[True], code_s[1:] != code_s[:-1]])
    if not ((rows_s[1:] == rows_s[:-1]).all(axis=1) | new[1:]).all():    # a group: equal rows
        mesh.merge_vertices(merge_tex=True, merge_norm=True)    # two rows with one hash: trimesh's way
        return
    group = np.cumsum(new) - 1
    first = np.minimum.reduceat(perm, np.flatnonzero(new))    # each group's first occurrence (rows of ``rows``)
    order = np.argsort(first)                   # groups in order of first occurrence
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    index = np.empty(len(rows), dtype=np.int64)
    index[perm] = rank[group]
    inverse = np.zeros(len(mesh.vertices), dtype=np.int64)
    inverse[referenced] = index
    mesh.update_vertices(mask=np.flatnonzero(referenced)[first[order]], inverse=inverse)


def _crossing_checked(mesh):
    """Whether :func:`_repair_crossings` looks for crossings in ``mesh``: a
    closed, consistently wound surface of at most
    :data:`SELF_INTERSECTION_MAX_TRIANGLES` triangles (any other is refused
    by :func:`validate_mesh`, or logged as not checked)."""
    return not (len(mesh.faces) > SELF_INTERSECTION_MAX_TRIANGLES or open_edge_count(mesh)
                or nonmanifold_edge_count(mesh) or not mesh.is_winding_consistent)


def crosses_itself(mesh):
    """Whether the surface of ``mesh`` (as :func:`load_model` returns it with
    ``crossings`` False) crosses itself where :func:`load_model` would have
    looked (:func:`_repair_crossings`): then loading with the search
    repairs it or refuses it.  A mesh found clean is marked as
    :func:`_repair_crossings` marks it (in this process: a caller that
    runs this in a worker marks its own copy, as :func:`ambots.job.run_job`
    does)."""
    from ambots.selfcross import crossing_pairs
    if not _crossing_checked(mesh):
        if len(mesh.faces) > SELF_INTERSECTION_MAX_TRIANGLES:
            check_self_intersection(mesh)          # logs that it is not checked
        return False
    if len(crossing_pairs(mesh)[0]):
        return True
    mesh.metadata[UNCROSSED_KEY] = hash(mesh)
    return False


def _repair_crossings(mesh, report):
    """Repair a closed surface that crosses itself when the defect is small
    (:func:`ambots.selfcross.repair_crossings`: the rule, and the refusal with
    the figure that failed); return the mesh (``mesh`` itself when it does
    not cross itself, or is not closed: :func:`validate_mesh` refuses it)."""
    from ambots.selfcross import repair_crossings
    from ambots.selfcross import crossing_pairs
    if not _crossing_checked(mesh):
        return mesh
    pairs, points = crossing_pairs(mesh)
    if not len(pairs):
        mesh.metadata[UNCROSSED_KEY] = hash(mesh)
        return mesh
    repaired = repair_crossings(mesh, source_name(mesh), report, pairs, points, mesh.metadata[REPAIRS_KEY])
    repaired.metadata.update(mesh.metadata)
    repaired.metadata[UNCROSSED_KEY] = hash(repaired)     # the repair checked it
    return repaired


def _fix_orientation(mesh):
    """Make winding consistent and outward; return how many faces flipped."""
    before = mesh.faces.copy()
    trimesh.repair.fix_winding(mesh)     # trimesh.repair.fix_normals, its volume without the inertia
    if mesh.is_watertight and signed_volume(mesh) < 0.0:
        mesh.invert()
    after = mesh.faces
    if len(before) != len(after):
        return 0
    # a face is unchanged if it is the same cyclic sequence of vertices
    same = np.zeros(len(after), dtype=bool)
    for shift in range(3):
        same |= (np.roll(before, shift, axis=1) == after).all(axis=1)
    return int((~same).sum())


def signed_volume(mesh):
    """``mesh.volume``, the same number (trimesh's first integral, summed the
    same way), without the centre of mass and inertia trimesh computes with it
    (0.17 s for 300,000 triangles)."""
    if not len(mesh.faces):
        return float(mesh.volume)
    tri = mesh.triangles
    f1 = tri[:, 0, 0] + tri[:, 1, 0] + tri[:, 2, 0]
    return float((mesh.triangles_cross[:, 0] * f1).sum() / 6.0)


def _merge_overlapping_shells(mesh):
    """Union shells that overlap (a self-intersecting mesh); return the mesh.

    Only closed, positive-volume shells are considered: a shell with a
    negative volume is a cavity and must stay a separate surface."""
    if not mesh.is_watertight or mesh.body_count < 2:
        return mesh
    shells = mesh.split(only_watertight=False)
    volumes = np.array([s.volume for s in shells])
    if (volumes <= 0).any():
        return mesh
    union = manifold3d.Manifold.batch_boolean([to_manifold(s) for s in shells],
                                              manifold3d.OpType.Add)
    overlap = volumes.sum() - union.volume()
    if overlap <= 1e-6 * volumes.sum():
        return mesh
    merged = from_manifold(union)
    merged.metadata.update(mesh.metadata)
    report = merged.metadata.get(REPORT_KEY)
    if report is not None:
        report.shells_merged = len(shells)
    merged.metadata[REPAIRS_KEY].append(
        "self-intersection: %d shells overlap by %.3f mm^3; merged into one volume"
        % (len(shells), overlap))
    return merged


# ------------------------------------------------------------- validation

def open_edge_count(mesh):
    """Number of edges used by exactly one triangle (boundary of a hole)."""
    return _edge_counts(mesh)[0]


def nonmanifold_edge_count(mesh):
    """Number of edges shared by more than two triangles."""
    return _edge_counts(mesh)[1]


def _kept(cache, mesh):
    """(hash of ``mesh``'s data, the value ``cache`` keeps for it while that
    data is unchanged, else None); (None, None) for what is not a trimesh
    (no weak reference or hash).  Store with ``cache[mesh] = (key, value)``."""
    try:
        key = hash(mesh)
        hit = cache.get(mesh)
    except TypeError:
        return None, None
    return key, (hit[1] if hit is not None and hit[0] == key else None)


#: the (open, non-manifold) edge counts of each live mesh, with the hash of
#: the mesh's data they were counted on: a load asks several times
_EDGE_COUNTS = weakref.WeakKeyDictionary()


def _edge_counts(mesh):
    """(edges used by one triangle, edges used by more than two) of
    ``mesh``, counted once while its data is unchanged."""
    key, hit = _kept(_EDGE_COUNTS, mesh)
    if hit is not None:
        return hit
    edges = np.asarray(mesh.edges_sorted, dtype=np.int64)
    counts = (0, 0)
    if len(edges):
        # one integer per edge (vertex indices are < the vertex count): sorting
        # integers is 5x faster than np.unique on rows
        code = np.sort(edges[:, 0] * (int(edges.max()) + 1) + edges[:, 1])
        starts = np.flatnonzero(np.concatenate([[True], code[1:] != code[:-1], [True]]))
        uses = np.diff(starts)
        counts = (int((uses == 1).sum()), int((uses > 2).sum()))
    if key is not None:
        _EDGE_COUNTS[mesh] = (key, counts)
    return counts


def validate_mesh(mesh, name=None, crossings=True):
    """Refuse a mesh that is not a closed, oriented volume.

    Checks, in order: open edges, non-manifold edges, inconsistent winding,
    zero volume, acceptance by manifold3d, no self-intersection
    (:func:`check_self_intersection`; not with ``crossings`` False:
    :func:`load_model`).  ``name`` defaults to the file name recorded by
    :func:`load_model`.
    """
    name = name or source_name(mesh)
    n_open = open_edge_count(mesh)
    if n_open:
        raise MeshError("%s: not a closed volume: %d open edges (edges of a hole, "
                        "used by one triangle only)" % (name, n_open))
    n_nonman = nonmanifold_edge_count(mesh)
    if n_nonman:
        raise MeshError("%s: not a closed volume: %d non-manifold edges (shared by "
                        "more than two triangles)" % (name, n_nonman))
    if not mesh.is_winding_consistent:
        raise MeshError("%s: triangles are not consistently oriented" % name)
    extent = float(np.max(mesh.extents)) if len(mesh.vertices) else 0.0
    with np.errstate(divide="ignore", invalid="ignore"):  # trimesh divides by it
        volume = signed_volume(mesh)
    if not abs(volume) > 1e-9 * max(extent, 1e-12) ** 3:
        raise MeshError("%s: zero volume (the mesh is flat or degenerate)" % name)
    if volume < 0:
        raise MeshError("%s: the normals point inward (negative volume %.3f mm^3)"
                        % (name, volume))
    to_manifold(mesh, name)  # raises when manifold3d does not accept it
    if crossings:
        check_self_intersection(mesh, name)


#: meshes with more triangles are not checked for self-intersections
#: (the cost, growing with the count: docs/pipeline.md, "Mesh repair")
SELF_INTERSECTION_MAX_TRIANGLES = 1_000_000


def check_self_intersection(mesh, name=None):
    """Refuse a surface that crosses itself (:func:`ambots.selfcross.self_intersections`:
    two triangles with no corner in common that intersect), naming where.

    Such a surface has no one inside: the slicer's outlines, the volume and
    the arms' split would each take a different one.  :func:`repair_mesh`
    has united shells that overlap each other, repaired a small crossing
    and refused a large one; what is left here is a mesh loaded without
    repair (or changed since).  A mesh :func:`repair_mesh` found clean and
    unchanged since is not checked again.  Meshes of more than
    :data:`SELF_INTERSECTION_MAX_TRIANGLES` triangles are not checked (logged)."""
    from ambots.selfcross import self_intersections
    name = name or source_name(mesh)
    if len(mesh.faces) > SELF_INTERSECTION_MAX_TRIANGLES:
        log.warning("%s: not checked for self-intersections: %s triangles, more than %s", name,
                    format(len(mesh.faces), ","), format(SELF_INTERSECTION_MAX_TRIANGLES, ","))
        return
    if mesh.metadata.get(UNCROSSED_KEY) == hash(mesh):
        return                           # checked by repair_mesh, unchanged since
    n, points = self_intersections(mesh, first=3)
    if n:
        raise MeshError("%s: the surface crosses itself: %d pair%s of triangles intersect, at %s mm (the "
                        "model's frame): inside and outside are ambiguous there; not repaired (load with "
                        "repair: a crossing small against the model is repaired, overlapping separate "
                        "shells are merged)" % (name, n, "" if n == 1 else "s",
                                         ", ".join("(%.2f, %.2f, %.2f)" % tuple(p) for p in points)
                                         + (", ..." if n > len(points) else "")))


def source_name(mesh):
    """The name used in messages for ``mesh`` (its file name when loaded)."""
    return mesh.metadata.get(SOURCE_KEY, "model") if mesh.metadata else "model"


# ------------------------------------------------------ placement and fit

def place_on_bed(mesh, bed_center_xy_mm=(0.0, 0.0), bed_z_mm=0.0):
    """A copy of ``mesh`` translated onto the bed.

    The centre of the axis-aligned bounding box goes to ``bed_center_xy_mm``
    in x and y, the lowest point to ``bed_z_mm`` (as the original project
    placed models).  The metadata is kept.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    bed_center_xy_mm : (2,) float
    bed_z_mm : float

    Returns
    -------
    placed : trimesh.Trimesh
    """
    lo, hi = mesh.bounds
    target = np.array([bed_center_xy_mm[0], bed_center_xy_mm[1], bed_z_mm], dtype=float)
    shift = target - np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    placed = mesh.copy()
    placed.apply_translation(shift)
    _carry_manifold(mesh, placed, shift)
    return placed


def check_fits(mesh, bed_size_xy_mm, max_height_mm):
    """Refuse a model larger than the bed or the printable height.

    Only sizes are compared (use :func:`place_on_bed` for the position).
    The message names every axis that overflows and by how much, e.g.
    "model is 230.0 mm wide in x, bed is 200.0 mm: 30.0 mm too large".
    """
    size = mesh.extents
    limits = (float(bed_size_xy_mm[0]), float(bed_size_xy_mm[1]), float(max_height_mm))
    what = (("wide in x", "bed is"), ("deep in y", "bed is"), ("high", "maximum height is"))
    errors = ["model is %.1f mm %s, %s %.1f mm: %.1f mm too large"
              % (s, w, lim_name, lim, s - lim)
              for s, lim, (w, lim_name) in zip(size, limits, what) if s > lim + 1e-9]
    if errors:
        raise MeshError("%s: does not fit: %s" % (source_name(mesh), "; ".join(errors)))


# ------------------------------------------------------------- manifold3d

#: the Manifold made of each live mesh, with the hash of the mesh's data it
#: was made from: a job converts its mesh for the split of every plan and for
#: the slicer (0.2 s each for 300,000 triangles)
_MANIFOLDS = weakref.WeakKeyDictionary()


def to_manifold(mesh, name=None):
    """A :class:`manifold3d.Manifold` of ``mesh`` (float64 vertices); the
    same (immutable) object again while the mesh's data is unchanged.

    Raises MeshError naming manifold3d's status when it refuses the mesh
    (not an oriented 2-manifold, non-finite vertex...)."""
    key, hit = _kept(_MANIFOLDS, mesh)
    if hit is not None:
        return hit
    m = manifold3d.Manifold(manifold3d.Mesh64(
        # copies: nanobind wants writeable C arrays, trimesh's may be read-only
        vert_properties=np.array(mesh.vertices, dtype=np.float64, order="C"),
        tri_verts=np.array(mesh.faces, dtype=np.uint64, order="C")))
    status = m.status()
    if status != manifold3d.Error.NoError:
        raise MeshError("%s: not a valid closed volume for manifold3d (%s)"
                        % (name or source_name(mesh), status.name))
    if key is not None:
        _MANIFOLDS[mesh] = (key, m)
    return m


def _carry_manifold(mesh, placed, shift):
    """Give ``placed`` (``mesh`` moved by ``shift``) the Manifold
    :func:`to_manifold` made of ``mesh``, moved, when it is the one
    :func:`to_manifold` would make of ``placed`` (the job's split reuses the
    load's, 0.3 s for 300,000 triangles): ``placed``'s vertices are exactly
    ``mesh``'s + ``shift`` (a moved Manifold adds the same numbers) and the
    largest coordinate does not shrink (manifold3d's tolerance grows with
    it, and a Manifold moved towards the origin keeps the larger one)."""
    hit = _MANIFOLDS.get(mesh)
    if hit is None or hit[0] != hash(mesh) or not len(mesh.vertices):
        return
    if np.abs(placed.bounds).max() < np.abs(mesh.bounds).max():
        return
    if not (np.array_equal(placed.faces, mesh.faces)
            and np.array_equal(placed.vertices, np.asarray(mesh.vertices) + shift)):
        return
    _MANIFOLDS[placed] = (hash(placed), hit[1] if not np.any(shift) else hit[1].translate(shift.tolist()))


def from_manifold(m):
    """A :class:`trimesh.Trimesh` of a :class:`manifold3d.Manifold`."""
    out = m.to_mesh64()
    return trimesh.Trimesh(vertices=np.array(out.vert_properties[:, :3], dtype=np.float64),
                           faces=np.array(out.tri_verts, dtype=np.int64), process=False)
