"""Where the arms wait when they do not print: their home poses, their park
positions clear of the bed (:func:`park_positions_mm`), and the joint moves
between a park position (or home) and the part (:class:`JointMoves`), which
the timeline counts in its steps' footprints.

Units: mm in the bed frame."""
import numpy as np

__all__ = ["home_positions_mm", "park_positions_mm", "JointMoves", "safe_height", "lift_height", "APPROACH_MM",
           "CLEAR_MM"]

#: a first move from home or the park position arrives this far (mm) over
#: the top of what is printed (then the nozzle goes straight down)
APPROACH_MM = 10.0
#: the arm's bodies keep at least this (mm) from the bed and the printed box on a
#: joint move between the part and home or the park position
CLEAR_MM = 5.0


def home_positions_mm(cell, arms):
    """Each arm's nozzle at its home pose, in bed-frame mm."""
    from ambots.kinematics import shared_arm_kinematics
    inv = np.linalg.inv(cell.bed.pose)
    out = {}
    for arm in arms:
        T = arm.base_pose @ shared_arm_kinematics(arm).fk(np.asarray(arm.profile.home))
        out[arm.name] = (inv[:3, :3] @ T[:3, 3] + inv[:3, 3]) * 1000.0
    return out


_PARKS = {}


def park_positions_mm(cell, arms, margin_mm=60.0):
    """Where each arm parks its nozzle (bed-frame mm): clear of the bed, on
    the arm's own side.

    From the arm's base (projected on the bed) towards the nearest point of
    the bed, the nozzle stops ``margin_mm`` short of the bed's edge, 50 mm
    over the printable height, so that the arm (base, links and nozzle)
    stays outside the bed and out of every other arm's way.  If the arm
    cannot reach that point with the nozzle down, points nearer to its base
    (or up to 30 mm nearer the bed) and higher are tried; an arm whose base
    stands over the bed, or that reaches none of them, parks at home."""
    from ambots.kinematics import shared_arm_kinematics
    from ambots.partition import arm_sites_mm
    from ambots.workspace import down_in_base, world_to_base
    arms = list(arms)
    key = (getattr(cell, "path", cell.name), tuple(a.name for a in arms), float(margin_mm))
    if key in _PARKS:
        return {k: v.copy() for k, v in _PARKS[key].items()}
    home = home_positions_mm(cell, arms)
    bx, by = cell.bed.size[0] * 500.0, cell.bed.size[1] * 500.0
    sites = dict(zip([a.name for a in arms], arm_sites_mm(cell, arms)))
    out = {}
    for arm in arms:
        h = np.asarray(home[arm.name], dtype=float)
        out[arm.name] = h
        site = np.asarray(sites[arm.name], dtype=float)
        nearest = np.clip(site, [-bx, -by], [bx, by])
        gap = float(np.linalg.norm(nearest - site))
        if gap < 1e-6:
            continue                                  # the base stands over the bed
        u = (nearest - site) / gap
        # where the ray from the base enters the bed grown by the margin
        lo, hi = np.array([-bx - margin_mm, -by - margin_mm]), np.array([bx + margin_mm, by + margin_mm])
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - site) / u, (hi - site) / u
        t_in = float(np.nanmax(np.where(np.abs(u) > 1e-12, np.minimum(t1, t2), -np.inf)))
        z0 = cell.bed.max_height * 1000.0 + 50.0
        cands = [np.array([*(site + u * r), z]) for r in (t_in, t_in - 40.0, t_in + 30.0, t_in - 80.0, t_in - 120.0)
                 if r >= 100.0 for z in (z0, z0 + 50.0, z0 + 100.0)]
        if not cands:
            continue
        P = np.array(cands)
        world = (P / 1000.0) @ cell.bed.pose[:3, :3].T + cell.bed.pose[:3, 3]
        _, ok, _ = shared_arm_kinematics(arm).ik_batch(world_to_base(arm, world), np.asarray(arm.profile.home),
                                                down_in_base(arm))
        if ok.any():
            out[arm.name] = P[int(np.argmax(ok))]
    _PARKS[key] = out
    return {k: v.copy() for k, v in out.items()}


class JointMoves:
    """Where the nozzle goes (bed frame, mm) on the joint moves the firmware
    makes between the park position (or home) and the part: a move to an
    A7 target, and a travel whose start is not where the nozzle is, are
    straight lines in joint space (:meth:`ambots.motion.MotionPlanner.
    joint_move_to`, nozzle-down IK seeded with the joints it starts from),
    which bulge off the straight line between their ends: a Panda coming
    down from its park position passed 21 mm nearer the seam than both
    ends.  :meth:`path` samples such a move; the timeline counts its points
    below the printable height in the step's footprint."""

    def __init__(self, cell, arms, samples=32):
        from ambots.kinematics import shared_arm_kinematics
        self.arm = {a.name: a for a in arms}
        self.kin = {a.name: shared_arm_kinematics(a) for a in arms}   # read only
        self.bed = np.asarray(cell.bed.pose, dtype=float)
        self.top = cell.bed.max_height * 1000.0
        self.cell = cell
        self.samples = int(samples)
        self._cache = {}
        self._bodies = {}

    def _ik(self, name, p_mm, seed):
        from ambots.workspace import down_in_base, world_to_base
        arm = self.arm[name]
        world = (np.asarray(p_mm, dtype=float) / 1000.0) @ self.bed[:3, :3].T + self.bed[:3, 3]
        Q, ok, _ = self.kin[name].ik_batch(world_to_base(arm, world[None]), np.asarray(seed, dtype=float),
                                           down_in_base(arm))
        return Q[0] if ok[0] else None

    def redundant(self, name):
        """Whether the arm has joints to spare for the nozzle's position, its
        direction and (with a ``trail``) its turn: then the joints it prints
        with depend on the path along the spare freedom (each IK starts from
        the joints before and turns towards the home posture by at most
        :data:`ambots.kinematics.POSTURE_RAD_PER_M`), and where it leaves the
        part no estimate follows them."""
        return self.kin[name].spare()

    def joints(self, name, a_mm, b_mm, park=False):
        """Joint vectors (samples, n) of the joint move from nozzle-down at
        ``a_mm`` (None: the arm's home pose) to nozzle-down at ``b_mm``
        (bed mm), or None if either end is out of reach.  ``park``: the
        move is an A7 (to the park position), whose end the firmware
        solves from the home pose (:meth:`ambots.motion.MotionPlanner.
        move_to`); otherwise from the move's start."""
        key = ("q", name, None if a_mm is None else tuple(np.round(a_mm, 6)), tuple(np.round(b_mm, 6)), park)
        if key not in self._cache:
            home = np.asarray(self.arm[name].profile.home, dtype=float)
            qa = home if a_mm is None else self._ik(name, a_mm, home)
            qb = None if qa is None else self._ik(name, b_mm, home if park else qa)
            if qb is None and qa is not None and park:
                qb = self._ik(name, b_mm, qa)
            Q = None
            if qb is not None:
                u = np.linspace(0.0, 1.0, self.samples)[:, None]
                Q = (1.0 - u) * qa + u * qb
            self._cache[key] = Q
        return self._cache[key]

    def path(self, name, a_mm, b_mm, park=False):
        """Nozzle positions (K, 3), bed mm, on the joint move from nozzle-down
        at ``a_mm`` (None: the arm's home pose) to nozzle-down at ``b_mm``
        (``park``: an A7, :meth:`joints`), only those at most at the
        printable height; empty if either end is out of reach (the firmware
        reports that itself)."""
        key = (name, None if a_mm is None else tuple(np.round(a_mm, 6)), tuple(np.round(b_mm, 6)), park)
        if key in self._cache:
            return self._cache[key]
        Q = self.joints(name, a_mm, b_mm, park)
        out = np.zeros((0, 3))
        if Q is not None:
            T = self.arm[name].base_pose @ self.kin[name].fk_batch(Q)
            inv = np.linalg.inv(self.bed)
            P = (T[:, :3, 3] @ inv[:3, :3].T + inv[:3, 3]) * 1000.0
            out = P[P[:, 2] <= self.top]
        self._cache[key] = out
        return out

    def _capsules(self, name, a_mm, b_mm, park):
        """The arm's capsules (A, B (K, C, 3) in the bed's frame, m; radii;
        the body) on the joint move of :meth:`joints`, or None."""
        from ambots.collision import ArmBody
        Q = self.joints(name, a_mm, b_mm, park)
        if Q is None:
            return None
        if name not in self._bodies:
            self._bodies[name] = ArmBody.from_arm(self.arm[name])
        body = self._bodies[name]
        A, B, r = body.capsules(Q)
        inv = np.linalg.inv(self.bed)
        return A @ inv[:3, :3].T + inv[:3, 3], B @ inv[:3, :3].T + inv[:3, 3], r, body

    def clearance_mm(self, name, a_mm, b_mm, box_lo_mm, box_hi_mm, park=False):
        """The smallest clearance (mm) of the arm's bodies (its collision
        capsules, :class:`ambots.collision.ArmBody`) to the bed (its link on
        the table left out, as :func:`ambots.collision.bed_clearance` does)
        and to the box ``box_lo_mm`` .. ``box_hi_mm`` (bed frame, mm: the
        part printed so far) on the joint move from ``a_mm`` (None: home) to
        ``b_mm`` (``park``: an A7, :meth:`joints`); None if either end is out
        of reach."""
        from ambots.collision import BED_SKIP, bed_box, box_clearance
        caps = self._capsules(name, a_mm, b_mm, park)
        if caps is None:
            return None
        A, B, r, body = caps
        bed = box_clearance(A, B, r, *bed_box(self.cell), body.mask(BED_SKIP))
        part = box_clearance(A, B, r, np.asarray(box_lo_mm) / 1000.0, np.asarray(box_hi_mm) / 1000.0)
        return float(min(bed.min(), part.min())) * 1000.0

    def clear(self, name, a_mm, b_mm, box_lo_mm, box_hi_mm, margin_mm, park=False):
        """Whether :meth:`clearance_mm` is at least ``margin_mm`` (False if
        either end is out of reach), answered from a bound where it can
        (:func:`ambots.collision.box_clear`): the schedule asks for every
        chunk it weighs after a park."""
        from ambots.collision import BED_SKIP, bed_box, box_clear
        caps = self._capsules(name, a_mm, b_mm, park)
        if caps is None:
            return False
        A, B, r, body = caps
        margin = float(margin_mm) / 1000.0
        return bool(box_clear(A, B, r, *bed_box(self.cell), margin, body.mask(BED_SKIP)).all()
                    and box_clear(A, B, r, np.asarray(box_lo_mm) / 1000.0, np.asarray(box_hi_mm) / 1000.0,
                                  margin).all())


def _heights(z_low, park_z):
    """The heights tried (mm), lowest first: ``z_low``, + 20, + 40, + 80
    under the park height, and the park height."""
    return sorted({z for z in (z_low, z_low + 20.0, z_low + 40.0, z_low + 80.0) if z < park_z} | {park_z})


def _lowest(z_low, park_z, clear):
    """The first height of :func:`_heights` for which ``clear(z)``, else the highest."""
    cands = _heights(z_low, park_z)
    return next((z for z in cands if clear(z)), cands[-1])


def safe_height(moves, name, start, xy, z_low, park_z, box):
    """The lowest height (mm) of ``z_low``, ``z_low`` + 20, + 40, + 80 and
    the park height at which the joint move between ``start`` (bed mm;
    None: home) and (``xy``, height) keeps :data:`CLEAR_MM` from the bed and
    the printed ``box`` ((lo, hi) bed mm); the highest if none does.
    ``moves``: :class:`JointMoves`, or None (no check: ``z_low``)."""
    if moves is None:
        return _heights(z_low, park_z)[0]
    return _lowest(z_low, park_z, lambda z: moves.clear(name, start, (xy[0], xy[1], z), *box, CLEAR_MM))


def lift_height(moves, name, p, park, z_low, box):
    """The height (mm) to lift the nozzle to, straight up from ``p`` (bed
    mm), before the A7 to the ``park`` position: the lowest of
    :func:`safe_height`'s over ``p`` from which the joint move to the
    park position keeps clear of the bed and the printed ``box``; the park
    position's height for an arm with joints to spare
    (:meth:`JointMoves.redundant`: where it leaves the part its joints are
    those of the print, which no estimate here follows; the Panda of the
    three-arm cell, 2.6 rad off on joints 1 and 3 after hours, swung 10 mm
    into the bed on its joint move to the park position from 10 mm over
    the part).  From there the swing stays over the printable height."""
    park_z = float(park[2])
    if moves is None or moves.redundant(name):
        return park_z if moves is not None else min(z_low, park_z)
    return _lowest(z_low, park_z, lambda z: moves.clear(name, (p[0], p[1], z), park, *box, CLEAR_MM, park=True))
