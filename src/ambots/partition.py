"""Split a model among the arms of a cell.

The parts are the cells of a *power diagram* of the arms' base positions on
the bed: part i holds the points p of the model with

    |p - s_i|^2 - w_i  <=  |p - s_j|^2 - w_j    for every other arm j,

s_i being arm i's base projected onto the bed (on a beam, clipped to the
bed: :func:`seam_sites_mm`).  Every boundary is a vertical plane
perpendicular to the line between two sites, so each arm gets the side of
the model that faces it, for any number of arms and any layout (two arms
facing each other get one plane, as in the original project; four in the
corners get a cross; a row of arms along a beam gets parallel planes across
it, also when the arms stand on alternate sides).  The
weights w_i move the planes until the arms' estimated print times balance.
The cuts are manifold3d half-space trims, so the parts are closed volumes
whose union is the model.  ``turn``: the sites turned about the model's
centre first, so every seam turns with them (two arms: the planner tries
the seam turned both ways, :data:`ambots.job.SEAM_TURNS_DEG`).

Seams: ``straight`` (the parts meet at the plane) or ``interlock`` (also
called ``overlap``): layer by layer the boundary alternates ``d`` either
side of the plane, so each arm's layers lap its neighbour's and no
vertical plane carries a junction on every layer (:mod:`ambots.seams`;
``d`` = :func:`ambots.seams.interlock_depth_mm`).  The parts still tile the
model: no volume is printed twice.  A part's ``planes`` are then the
planes it never crosses (the seam plane moved ``d`` into the neighbour).

Units: millimetres in the bed frame (the G-code frame: origin at the centre
of the bed's top surface, z up).
"""
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np

from ambots.errors import MeshError
from ambots.units import MM, m_to_mm

__all__ = ["Part", "PrintEstimate", "partition", "arm_sites_mm", "seam_sites_mm", "estimate_print_time", "is_beam",
           "turned"]

#: a bed whose long side is at least this many times its short side is a beam:
#: the power diagram's sites are clipped to it (:func:`seam_sites_mm`)
BEAM_ASPECT = 3.0


@dataclass(frozen=True)
class PrintEstimate:
    """What the balance needs to know about how a part will be printed."""
    bead_width: float = 0.45       #: mm
    layer_height: float = 0.2      #: mm
    perimeters: int = 2
    infill_density: float = 0.2    #: 0..1
    speed: float = 40.0            #: mm/s while extruding


def estimate_print_time(manifold, est=PrintEstimate()):
    """Seconds to print a closed volume: walls (surface x wall thickness) at
    full density, the rest at the infill density, laid as beads of
    ``bead_width`` x ``layer_height`` at ``speed``."""
    volume = manifold.volume()
    if volume <= 0:
        return 0.0
    walls = min(volume, manifold.surface_area() * est.bead_width * est.perimeters)
    deposit = walls + (volume - walls) * est.infill_density
    return deposit / (est.bead_width * est.layer_height * est.speed)


@dataclass
class Part:
    arm: object                    #: the ArmInstance that prints it
    manifold: object               #: manifold3d.Manifold, mm, bed frame
    planes: List[Tuple[np.ndarray, float]] = field(default_factory=list)  #: kept side: n . p >= offset
    est_time_s: float = 0.0
    #: the arm on the other side of each plane (``planes[j]`` is the boundary
    #: with arm ``neighbours[j]``, an arm name), in the same order as ``planes``
    neighbours: List[str] = field(default_factory=list)
    #: a stepped seam (:mod:`ambots.seam_steps`): per slicer layer, mm added
    #: to the offset of each of :attr:`planes` on that layer (None: straight)
    layer_offsets: Optional[np.ndarray] = None

    @property
    def volume(self):
        return self.manifold.volume()

    @property
    def empty(self):
        return self.manifold.is_empty() or self.manifold.volume() <= 0

    def to_trimesh(self):
        import trimesh
        m = self.manifold.to_mesh()
        return trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts), process=False)


def arm_sites_mm(cell, arms):
    """Arm base positions projected onto the bed, (N, 2) mm in the bed frame."""
    T = np.linalg.inv(cell.bed.pose)
    pts = np.array([T[:3, :3] @ a.base_xyz + T[:3, 3] for a in arms])
    return m_to_mm(pts[:, :2])


def is_beam(cell):
    """Whether the cell's bed is a beam: at least :data:`BEAM_ASPECT` times
    as long as it is wide."""
    sx, sy = m_to_mm(np.asarray(cell.bed.size[:2], dtype=float))
    return max(sx, sy) >= BEAM_ASPECT * min(sx, sy)


def seam_sites_mm(cell, arms):
    """The sites of the power diagram, (N, 2) mm in the bed frame: the arms'
    bases projected onto the bed (:func:`arm_sites_mm`), on a beam (a bed at
    least :data:`BEAM_ASPECT` times as long as it is wide) clipped to the
    bed.  Arms on alternate sides of a beam then get seams across the beam
    (the line between two clipped sites runs almost along it) instead of
    seams slanted along it: two nozzles a given distance apart across a
    slanted seam are 2-3 times that far apart along the beam, so the seam
    zone would cover most of each part."""
    sites = arm_sites_mm(cell, arms)
    if is_beam(cell):
        sx, sy = m_to_mm(np.asarray(cell.bed.size[:2], dtype=float))
        sites = np.clip(sites, [-sx / 2, -sy / 2], [sx / 2, sy / 2])
    return sites


def turned(points, centre, turn):
    """(N, 2) ``points`` turned by ``turn`` (rad, counter-clockwise) about
    ``centre`` (2,)."""
    c, s = np.cos(turn), np.sin(turn)
    return (np.asarray(points, dtype=float) - centre) @ np.array([[c, s], [-s, c]]) + centre


def _planes(sites, weights, i, shift=0.0):
    """Half-spaces (n, offset) of power cell i, one per other site j in the
    order of ``sites`` (j != i); ``shift`` (mm) moves each plane outward (into
    the neighbour)."""
    out = []
    for j in range(len(sites)):
        if j == i:
            continue
        d = sites[i] - sites[j]
        L = float(np.linalg.norm(d))
        n = np.array([d[0] / L, d[1] / L, 0.0])
        off = (sites[i] @ sites[i] - sites[j] @ sites[j] + weights[j] - weights[i]) / (2 * L)
        out.append((n, off - shift))
    return out


def _cut(model, planes):
    part = model
    for n, off in planes:
        part = part.trim_by_plane(n.tolist(), float(off))
    return part


def partition(model, cell, arms=None, seam="straight", est=PrintEstimate(), tolerance=None,
              max_iter=80, check_reach=True, reach_cache=None, layers=None, interlock_mm=None, pace=None,
              turn=0.0):
    """Split ``model`` (manifold3d.Manifold, mm, bed frame) among ``arms`` (default:
    every arm of ``cell``) and return one :class:`Part` per arm, in order.

    The weights are adjusted until the longest estimated print time is within
    ``tolerance`` of the shortest (or ``max_iter`` rounds; default 1.005 for
    two arms, whose one seam is found by the secant method, else 1.02); ``pace``:
    {arm name: how long it takes relative to the others for the same
    work} (default 1: all alike), e.g. the arms' times for the whole model
    (the job's plans of each arm alone) over their mean, so a slower arm
    gets a smaller part.  With
    ``check_reach``, every vertex of every part must be reachable by its arm
    with the nozzle down (:func:`_check_reach`: what is solved, and why that
    is safe); otherwise :class:`MeshError` says which arm misses by how much.
    ``reach_cache``: a dict kept by the caller across calls on the same model
    (a job's plans): a point already checked for an arm is not solved again.
    ``turn`` (rad, counter-clockwise): the sites turned about the centre of
    the model's bounding box (:func:`turned`) before the split, so the
    seams between the parts turn by as much (several arms).

    ``seam``: ``straight``, or ``interlock`` / ``overlap`` (the same, see the
    module docstring): then ``layers`` = (z_tops, heights) (L,) mm, the
    slicer's layers (default: :func:`ambots.slicer.layer_heights` of the
    default settings with ``est``'s layer height), and ``interlock_mm`` the
    depth d (default :func:`ambots.seams.interlock_depth_mm` of ``est``).
    """
    from ambots.seams import interlock_depth_mm, interlock_pieces, seam_kind
    arms = list(cell.arms if arms is None else arms)
    kind = seam_kind(seam)
    if model.is_empty() or model.volume() <= 0:
        raise MeshError("nothing to partition: the model is empty")
    if len(arms) == 1:
        parts = [Part(arms[0], model, [], estimate_print_time(model, est), [])]
    else:
        rates = [float((pace or {}).get(a.name, 1.0)) for a in arms]
        lo, hi = np.array(model.bounding_box()[:2]), np.array(model.bounding_box()[3:5])
        centre = (lo + hi) / 2
        sites = seam_sites_mm(cell, arms)
        if turn:
            sites = turned(sites, centre, float(turn))
        size2 = float(np.sum((hi - lo) ** 2))
        # start with every boundary through the model's centre
        w = np.sum((sites - centre) ** 2, axis=1)
        best = None
        step = 0.5
        prev_sign = None
        two = len(arms) == 2
        if tolerance is None:
            tolerance = 1.005 if two else 1.02
        prev = None                  # two arms: (w[0], rel[0]) of the round before, for the secant
        for _ in range(max_iter):
            pieces = [_cut(model, _planes(sites, w, i)) for i in range(len(arms))]
            times = np.array([estimate_print_time(piece, est) * rate for piece, rate in zip(pieces, rates)])
            ratio = times.max() / max(times.min(), 1e-9)
            if best is None or ratio < best[0]:
                best = (ratio, w.copy(), pieces, times)
            if ratio <= tolerance:
                break
            rel = (times - times.mean()) / times.mean()
            if two and prev is not None and abs(rel[0] - prev[1]) > 1e-12 and w[0] != prev[0]:
                slope = (rel[0] - prev[1]) / (w[0] - prev[0])
                if slope > 0:        # a larger weight, a larger part: the secant's root
                    prev = (w[0], rel[0])
                    w = w.copy()
                    w[0] -= rel[0] / slope
                    continue
            sign = np.sign(rel)
            if prev_sign is not None and np.any(sign * prev_sign < 0):
                step *= 0.7          # overshoot: take smaller steps
            prev_sign = sign
            prev = (w[0], rel[0])
            w = w - step * rel * size2
        w = best[1]
        # the best round's pieces are the parts of a straight seam, and their times
        pieces = best[2]
        shift = 0.0
        if kind == "interlock":
            shift = interlock_depth_mm(est.bead_width, est.layer_height) if interlock_mm is None else interlock_mm
            if not shift > 0:
                raise ValueError("interlock_mm must be > 0, got %r" % interlock_mm)
            if layers is None:
                from ambots.slicer import SliceSettings, layer_heights
                layers = layer_heights(float(model.bounding_box()[5]),
                                       SliceSettings(layer_height_mm=est.layer_height,
                                                     first_layer_height_mm=est.layer_height,
                                                     bead_width_mm=est.bead_width))
            pieces = interlock_pieces(model, [_planes(sites, w, i) for i in range(len(arms))], shift, *layers)
        parts = []
        for i, arm in enumerate(arms):
            parts.append(Part(arm, pieces[i], _planes(sites, w, i, shift), float(best[3][i]),
                              [a.name for j, a in enumerate(arms) if j != i]))
    if check_reach:
        for part in parts:
            _check_reach(cell, part, reach_cache)
    return parts


def check_part_reach(cell, part, cache=None):
    """Refuse (MeshError) a part whose arm cannot reach every vertex of it
    with the nozzle down, as :func:`partition` checks its parts (there:
    what is solved, and why that is safe)."""
    _check_reach(cell, part, cache)


#: side (mm) of the cubes of the bed-frame grid of :func:`_check_reach`: a vertex
#: whose cube has its eight corners in reach is not solved on its own
REACH_CELL_MM = 2.0


def _check_reach(cell, part, cache=None, exhaustive=False):
    """Refuse (MeshError) a part whose arm cannot put the nozzle, pointing
    down, on every vertex of the part: the message says how many of the
    part's vertices miss, the worst one (bed frame, mm) and by how much.

    The rule (what is solved): the vertices are binned in the cubes of a
    grid of side :data:`REACH_CELL_MM` fixed to the bed (the same corners
    for every part and plan of a job: ``cache``); the inverse kinematics
    (from the home pose, as for a vertex) is solved at the corners of the
    occupied cubes, and a vertex whose cube has its eight corners in reach
    is in reach.  The vertices of the other cubes are solved one by one, so
    every miss is found, counted and measured as by solving every vertex
    (``exhaustive``: what the tests compare with).  Why it is safe: where
    the set the nozzle reaches pointing down is convex around a cube (the
    outer reach, a joint limit bounding it), a vertex outside it has a plane
    between it and the set, and the corner of its cube farthest along that
    plane's normal is outside too: a vertex that misses by any amount leaves
    a corner of its cube unsolvable, so its cube is solved vertex by vertex.
    Where the border is concave (the hole about the base's axis, of radius
    R), a sphere keeping out the eight corners of a cube of side h pokes into
    it by less than h^2 / (4 R) (0.01 mm for h = 2 mm and R = 100 mm): a
    vertex can miss by that much unnoticed.  (A vertex in reach that the
    solver from the home pose fails on, which solving every vertex refused,
    is accepted when its cube's corners are solved.)  The check of vertices
    alone never looked between them (a face of a 200 mm box is checked at
    its corners), this grid looks at most h * sqrt(3) away from every vertex.
    When the corners are more than a quarter of the vertices (a coarse mesh,
    or a large one: a corner costs as much as a vertex), the vertices are
    solved."""
    from ambots.kinematics import shared_arm_kinematics
    from ambots.workspace import down_in_base, world_to_base
    if part.empty:
        return
    mesh = part.manifold.to_mesh()
    props = np.asarray(mesh.vert_properties)[:, :3]
    v = props * MM                                                   # bed frame, m
    to_world = lambda P: P @ cell.bed.pose[:3, :3].T + cell.bed.pose[:3, 3]
    arm = part.arm
    kin = shared_arm_kinematics(arm)
    solve = lambda W: kin.ik_batch(world_to_base(arm, W), np.asarray(arm.profile.home), down_in_base(arm))[1:]
    known = None if cache is None else cache.setdefault((arm.name, id(kin), id(cell)), {})
    reach = solve if known is None else (lambda W: _cached_reach(known, W, solve))
    todo = np.ones(len(v), dtype=bool)                               # the vertices to solve
    if not exhaustive:
        # one integer per grid point (21 bits an axis: +-2 km at 2 mm), sorting integers, not rows
        cube = np.floor(np.asarray(props, dtype=np.float64) / REACH_CELL_MM).astype(np.int64) + _GRID_HALF
        cubes, of_vertex = np.unique((cube[:, 0] << 42) | (cube[:, 1] << 21) | cube[:, 2], return_inverse=True)
        corners, of_corner = np.unique((cubes[:, None] + _CUBE_CORNERS[None]).ravel(), return_inverse=True)
        if 4 * len(corners) <= len(v):
            xyz = np.stack([corners >> 42, (corners >> 21) & _GRID_MASK, corners & _GRID_MASK], axis=1) - _GRID_HALF
            ok_c = reach(to_world(xyz * (REACH_CELL_MM * MM)))[0]
            cube_ok = ok_c[of_corner.reshape(-1)].reshape(-1, 8).all(axis=1)
            todo = ~cube_ok[of_vertex.reshape(-1)]
    ok, err = np.ones(len(v), dtype=bool), np.zeros(len(v))
    if todo.any():
        ok[todo], err[todo] = reach(to_world(v[todo]))
    if not ok.all():
        worst = int(np.argmax(np.where(ok, -1.0, err)))
        raise MeshError("the part for arm %r has %d of %d corners out of its reach; worst at "
                        "(%.1f, %.1f, %.1f) mm on the bed, missed by %.1f mm"
                        % (arm.name, (~ok).sum(), len(ok), *m_to_mm(v[worst]), m_to_mm(err[worst])))


#: the eight corners of a grid cube, as offsets of its lowest corner's key (21 bits an axis)
_CUBE_CORNERS = np.array([(i << 42) | (j << 21) | k for i in (0, 1) for j in (0, 1) for k in (0, 1)],
                         dtype=np.int64)
_GRID_MASK = (1 << 21) - 1
_GRID_HALF = 1 << 20


def _cached_reach(known, world, solve):
    """(ok, err) of the points ``world`` (N, 3), solving only those not in
    ``known`` ({point's bytes: (ok, err)}, updated).  Each point's IK is
    solved on its own (same seed, same target), so a stored answer is the
    one solving it again would give."""
    keys = np.ascontiguousarray(world).view(np.dtype((np.void, world.dtype.itemsize * 3))).ravel().tolist()
    hit = [known.get(k) for k in keys]
    todo = np.array([h is None for h in hit], dtype=bool)
    ok, err = np.zeros(len(keys), dtype=bool), np.zeros(len(keys))
    if (~todo).any():
        old = np.array([h for h in hit if h is not None], dtype=float).reshape(-1, 2)
        ok[~todo], err[~todo] = old[:, 0] > 0, old[:, 1]
    if todo.any():
        ok_new, err_new = solve(world[todo])
        ok[todo], err[todo] = ok_new, err_new
        known.update(zip([k for k, t in zip(keys, todo) if t], zip(ok_new.tolist(), err_new.tolist())))
    return ok, err
