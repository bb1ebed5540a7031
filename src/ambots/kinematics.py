"""Kinematics of one arm, from its URDF.

* :func:`chain_from_urdf` -- URDF string -> :class:`Chain` (a serial chain of
  fixed / revolute / continuous / prismatic segments), parsed with yourdfpy.
* :func:`kdl_chain` -- :class:`Chain` -> ``PyKDL.Chain`` (what kdl_parser does;
  kdl_parser_py is not packaged on Debian).
* :class:`ArmKinematics` -- forward kinematics (KDL for one configuration,
  vectorised numpy for many: ``(N, n)`` joint vectors -> ``(N, 4, 4)`` poses),
  geometric Jacobians, and inverse kinematics for a nozzle *position* plus a
  nozzle *axis direction* (usually straight down).  The rotation about the
  nozzle axis is left free, or, for a print head whose nozzle sits off the
  flange's axis (``trail``), chosen so that the flange stays on the side of
  the arm's base: the wrist and forearm trail behind the nozzle.  IK is
  seeded, respects joint limits and reports failure instead of returning
  garbage.

The IK is a damped least-squares Newton iteration on a 5-row task (3 position
rows, 2 rows for the tilt of the nozzle axis; a 6th row for the turn about
the nozzle axis with a ``trail``), run on many targets at once.
:meth:`ArmKinematics.ik_path` solves a densely sampled toolpath by solving
sparse key points one after the other (each seeded by the previous one), then
refining every point at once from seeds interpolated between the keys.  An
arm with joints to spare (more joints than task rows: the Panda's seven for
six) would drift along its self-motion, each key seeded by the one before;
with a ``rest`` posture (the profile's home) each key after the first also
steps along the self-motion towards it (:data:`POSTURE_RAD_PER_M`), so the
joints at a nozzle position no longer depend on how long the arm printed.

Units: metres and radians.  All poses are in the arm's base frame.
"""
import io
import math
from typing import List, NamedTuple, Optional

import numpy as np

from ambots.errors import KinematicsError, UnreachableError

__all__ = ["Segment", "Chain", "chain_from_urdf", "kdl_chain", "ArmKinematics", "DOWN", "trail_targets",
           "shared_arm_kinematics"]

#: nozzle pointing straight down in a base frame whose z axis is up
DOWN = np.array([0.0, 0.0, -1.0])

#: how fast :meth:`ArmKinematics.ik_path` turns a redundant arm along its
#: self-motion towards its rest posture: at most this many radians (on any
#: joint) per metre of the nozzle's path.  At 40 mm/s that is 0.04 rad/s of
#: self-motion, next to the Panda's 1.09 rad/s (its limit at velocity scaling
#: 0.5), so the timing law does not slow a print for it; a 2.4 rad drift is
#: undone within 2.4 m of path (a layer of a 150 mm part).  Session 22: the
#: Panda, 20 passes over a 200 x 200 mm square: joints 1 and 3 at the start of
#: a pass had wandered up to 2.4 rad without it, under 0.0005 rad with it.
POSTURE_RAD_PER_M = 1.0


class Segment(NamedTuple):
    """One link of a serial chain: the joint's ``origin`` (4x4, parent link
    frame -> joint frame at q = 0), its ``kind`` (``fixed``, ``revolute``,
    ``continuous`` or ``prismatic``), unit ``axis`` (3,) in the joint frame, the
    joint's name and the child link's name."""
    joint: str
    link: str
    kind: str
    origin: np.ndarray
    axis: np.ndarray


class Chain(NamedTuple):
    """A serial chain from ``base`` to ``tip`` with its joint limits (rad or m;
    +-inf for continuous joints) and speed limits (rad/s or m/s), in the order
    of the movable joints along the chain."""
    base: str
    tip: str
    segments: List[Segment]
    joint_names: List[str]
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray

    @property
    def dof(self):
        return len(self.joint_names)


_MOVABLE = ("revolute", "continuous", "prismatic")


def chain_from_urdf(urdf_xml, base, tip):
    """Parse a URDF string and extract the serial chain ``base`` -> ``tip``.

    Raises :class:`KinematicsError` for malformed URDF, unknown links, a tip
    that does not descend from the base, or unsupported joint types.
    """
    import xml.etree.ElementTree as ET

    import yourdfpy
    data = urdf_xml.encode() if isinstance(urdf_xml, str) else urdf_xml
    try:  # strict XML first: yourdfpy silently "recovers" truncated documents
        ET.fromstring(data)
    except ET.ParseError as exc:
        raise KinematicsError("malformed URDF: %s" % exc) from None
    try:
        robot = yourdfpy.URDF.load(io.BytesIO(data), build_scene_graph=False, load_meshes=False,
                                   build_collision_scene_graph=False, load_collision_meshes=False).robot
    except (yourdfpy.URDFError, ValueError, TypeError, SyntaxError) as exc:  # lxml's errors are SyntaxErrors
        raise KinematicsError("malformed URDF: %s" % exc) from None
    links = {l.name for l in robot.links}
    for name, what in ((base, "base"), (tip, "tip")):
        if name not in links:
            raise KinematicsError("URDF of robot %r has no %s link %r" % (robot.name, what, name))
    by_child = {j.child: j for j in robot.joints}
    path = []
    link = tip
    while link != base:
        if link not in by_child:
            raise KinematicsError("link %r does not descend from %r in robot %r" % (tip, base, robot.name))
        j = by_child[link]
        path.append(j)
        link = j.parent
    path.reverse()
    segments, names, lower, upper, vel = [], [], [], [], []
    for j in path:
        if j.type not in _MOVABLE + ("fixed",):
            raise KinematicsError("joint %r: type %r is not supported in a serial arm" % (j.name, j.type))
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=float)
        axis = np.array([1.0, 0.0, 0.0]) if j.axis is None else np.asarray(j.axis, dtype=float)
        if j.type != "fixed":
            norm = np.linalg.norm(axis)
            if not norm > 0:
                raise KinematicsError("joint %r has a zero axis" % j.name)
            axis = axis / norm
            names.append(j.name)
            lim = j.limit
            if j.type == "continuous" or lim is None or lim.lower is None or lim.upper is None:
                if j.type != "continuous":
                    raise KinematicsError("joint %r (%s) has no position limits" % (j.name, j.type))
                lower.append(-np.inf)
                upper.append(np.inf)
            else:
                lower.append(float(lim.lower))
                upper.append(float(lim.upper))
            vel.append(float(lim.velocity) if lim is not None and lim.velocity else np.inf)
        segments.append(Segment(j.name, j.child, j.type, origin, axis))
    return Chain(base, tip, segments, names, np.array(lower), np.array(upper), np.array(vel))


def kdl_chain(chain):
    """:class:`Chain` -> ``PyKDL.Chain`` with one KDL segment per URDF joint,
    named after the child link (as kdl_parser does)."""
    import PyKDL as kdl
    out = kdl.Chain()
    for s in chain.segments:
        f = _kdl_frame(s.origin)
        if s.kind == "fixed":
            joint = kdl.Joint(s.joint, kdl.Joint.Fixed)
        else:
            kind = kdl.Joint.TransAxis if s.kind == "prismatic" else kdl.Joint.RotAxis
            joint = kdl.Joint(s.joint, f.p, f.M * kdl.Vector(*s.axis), kind)
        out.addSegment(kdl.Segment(s.link, joint, f))
    return out


def _kdl_frame(T):
    import PyKDL as kdl
    R = T[:3, :3]
    return kdl.Frame(kdl.Rotation(*R.ravel().tolist()), kdl.Vector(*T[:3, 3].tolist()))


def _cross(a, b):
    """Row-wise cross product of (N, 3) arrays (np.cross is slow on small rows)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _rodrigues(axis, q):
    """Rotation matrices about unit ``axis`` (3,) by angles ``q`` (N,) -> (N, 3, 3)."""
    x, y, z = axis
    K = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    s, c = np.sin(q)[:, None, None], np.cos(q)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


class ArmKinematics:
    """Forward and inverse kinematics of one arm, base frame -> tool (nozzle).

    Parameters
    ----------
    chain : Chain
        From :func:`chain_from_urdf`; its tip is the tool frame (the nozzle).
    tool_axis : (3,) array
        The nozzle's pointing direction in the tool frame (its z axis).
    trail : (3,) array or None
        A direction in the tool frame, perpendicular to ``tool_axis`` (for an
        offset print head: from the nozzle towards the flange's axis).  With
        it the IK also fixes the turn about the nozzle axis: ``trail`` points
        (in the plane perpendicular to the nozzle axis) towards the base
        frame's z axis, so the flange, wrist and forearm stay between the
        nozzle and the arm's base (:func:`trail_targets`).  None: that turn
        is free (the iteration's least-norm step keeps it near the seed).
    rest : (n,) array or None
        The posture an arm with joints to spare returns to along its
        self-motion while :meth:`ik_path` follows a path (the profile's home,
        :func:`ambots.model.arm_kinematics`); None: none (each key point
        stays as near its seed as the least-norm step leaves it).
    """

    def __init__(self, chain, tool_axis=(0.0, 0.0, 1.0), trail=None, rest=None):
        if chain.dof == 0:
            raise KinematicsError("chain %s -> %s has no movable joint" % (chain.base, chain.tip))
        self.chain = chain
        self.tool_axis = np.asarray(tool_axis, dtype=float)
        self.trail = None
        if trail is not None:
            t = np.asarray(trail, dtype=float)
            t = t - (t @ self.tool_axis) * self.tool_axis / (self.tool_axis @ self.tool_axis)
            if not np.linalg.norm(t) > 1e-9:
                raise KinematicsError("trail %s is parallel to the tool axis %s" % (list(trail), list(tool_axis)))
            self.trail = t / np.linalg.norm(t)
        self.lower, self.upper = chain.lower, chain.upper
        # pre-computed per-segment data for the vectorised FK
        self._plan = []
        qi = 0
        for s in chain.segments:
            if s.kind == "fixed":
                self._plan.append((s.origin, None, None, False))
            else:
                zaxis = bool(np.allclose(s.axis, (0, 0, 1)))
                self._plan.append((s.origin, qi, s.axis, zaxis if s.kind != "prismatic" else None))
                qi += 1
        self._movable = [p for p in self._plan if p[1] is not None]
        # the same plan as plain floats, for one target at a time (_ik_one):
        # (R of the origin row-major, its translation, joint index, axis, zaxis)
        self._plan_py = [(tuple(float(v) for v in o[:3, :3].ravel()), tuple(float(v) for v in o[:3, 3]), qi,
                          None if ax is None else tuple(float(v) for v in ax), z)
                         for o, qi, ax, z in self._plan]
        self._lower_py = [float(v) for v in self.lower]
        self._upper_py = [float(v) for v in self.upper]
        self._kdl = None
        self.rest = None
        if rest is not None:
            self.rest = np.asarray(rest, dtype=float).reshape(-1)
            if len(self.rest) != chain.dof:
                raise KinematicsError("rest posture has %d joints, the chain %d" % (len(self.rest), chain.dof))

    @classmethod
    def from_urdf(cls, urdf_xml, base="base_link", tip="nozzle", prefix="", tool_axis=(0.0, 0.0, 1.0), trail=None,
                  rest=None):
        """Build from a URDF string; ``prefix`` is prepended to ``base`` and ``tip``."""
        return cls(chain_from_urdf(urdf_xml, prefix + base, prefix + tip), tool_axis, trail, rest)

    @property
    def dof(self):
        return self.chain.dof

    @property
    def joint_names(self):
        return list(self.chain.joint_names)

    # ------------------------------------------------------------------ KDL
    def _kdl_solvers(self):
        if self._kdl is None:
            import PyKDL as kdl
            ch = kdl_chain(self.chain)
            # keep the chain referenced: KDL solvers hold it by reference
            self._kdl = (ch, kdl.ChainFkSolverPos_recursive(ch))
        return self._kdl

    def fk(self, q):
        """Tool pose (4x4) at one joint vector ``q`` (n,), computed by KDL."""
        import PyKDL as kdl
        ch, fk = self._kdl_solvers()
        q = np.asarray(q, dtype=float)
        if q.shape != (self.dof,):
            raise ValueError("expected %d joint values, got shape %s" % (self.dof, q.shape))
        jq = kdl.JntArray(self.dof)
        for i, v in enumerate(q):
            jq[i] = float(v)
        f = kdl.Frame()
        if fk.JntToCart(jq, f) < 0:
            raise KinematicsError("KDL forward kinematics failed")
        T = np.eye(4)
        T[:3, :3] = [[f.M[i, j] for j in range(3)] for i in range(3)]
        T[:3, 3] = [f.p[0], f.p[1], f.p[2]]
        return T

    # ------------------------------------------------------- vectorised FK
    #: from this many joint vectors on, :meth:`_forward` keeps the rotations
    #: as rows of (N,) vectors (:meth:`_forward_rows`): 2.5-3x faster on
    #: thousands of poses (a model's corners), slower on a few
    ROWS_FROM = 64

    def _forward(self, Q, frames=False, jacobian=False):
        Q = np.asarray(Q, dtype=float)
        N = Q.shape[0]
        if N >= self.ROWS_FROM and not frames:
            return self._forward_rows(Q, jacobian)
        T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
        link_frames = [T.copy()] if frames else None
        axes, points = [], []
        for origin, qi, axis, zaxis in self._plan:
            T = T @ origin
            if qi is not None:
                q = Q[:, qi]
                if jacobian:
                    axes.append(T[:, :3, :3] @ axis)
                    points.append(T[:, :3, 3].copy())
                if zaxis is None:          # prismatic
                    T[:, :3, 3] += (T[:, :3, :3] @ axis) * q[:, None]
                elif zaxis:                # rotation about local z: mix columns 0 and 1
                    c, s = np.cos(q)[:, None], np.sin(q)[:, None]
                    x, y = T[:, :3, 0].copy(), T[:, :3, 1]
                    T[:, :3, 0] = c * x + s * y
                    T[:, :3, 1] = c * y - s * x
                else:
                    T[:, :3, :3] = T[:, :3, :3] @ _rodrigues(axis, q)
            if frames:
                link_frames.append(T.copy())
        J = None
        if jacobian:
            J = np.empty((N, 6, self.dof))
            tip = T[:, :3, 3]
            for k, ((origin, qi, axis, zaxis), z, p) in enumerate(
                    zip(self._movable, axes, points)):
                if zaxis is None:
                    J[:, :3, k] = z
                    J[:, 3:, k] = 0.0
                else:
                    J[:, :3, k] = _cross(z, tip - p)
                    J[:, 3:, k] = z
        return T, (np.stack(link_frames, axis=1) if frames else None), J

    def _forward_rows(self, Q, jacobian=False):
        """:meth:`_forward` (without frames) with the rotation kept as R[i, j]
        (N,) vectors, (3, 3, N), and the position as (3, N): each step is a
        few whole-vector operations instead of N small matrix products."""
        N = Q.shape[0]
        R = np.zeros((3, 3, N))
        R[0, 0] = R[1, 1] = R[2, 2] = 1.0
        p = np.zeros((3, N))
        axes, points = [], []
        for origin, qi, axis, zaxis in self._plan:
            # T @ origin: p += R @ o_p, R = R @ o_R (row i of R times o_R)
            p = p + (R[:, 0] * origin[0, 3] + R[:, 1] * origin[1, 3] + R[:, 2] * origin[2, 3])
            R = np.matmul(origin[:3, :3].T, R)
            if qi is None:
                continue
            q = Q[:, qi]
            if jacobian or zaxis is None:
                z = R[:, 0] * axis[0] + R[:, 1] * axis[1] + R[:, 2] * axis[2]
            if jacobian:
                axes.append(z)
                points.append(p)
            if zaxis is None:          # prismatic
                p = p + z * q
            elif zaxis:                # rotation about local z: mix columns 0 and 1
                c, s = np.cos(q), np.sin(q)
                x, y = R[:, 0], R[:, 1]
                R = np.stack([c * x + s * y, c * y - s * x, R[:, 2]], axis=1)
            else:
                G = _rodrigues(axis, q).transpose(1, 2, 0)          # (3, 3, N)
                R = R[:, 0, None] * G[0] + R[:, 1, None] * G[1] + R[:, 2, None] * G[2]
        T = np.zeros((N, 4, 4))
        T[:, :3, :3] = R.transpose(2, 0, 1)
        T[:, :3, 3] = p.T
        T[:, 3, 3] = 1.0
        J = None
        if jacobian:
            J = np.empty((N, 6, self.dof))
            for k, ((_, _, _, zaxis), z, pk) in enumerate(zip(self._movable, axes, points)):
                if zaxis is None:
                    J[:, :3, k] = z.T
                    J[:, 3:, k] = 0.0
                else:
                    r = p - pk
                    J[:, 0, k] = z[1] * r[2] - z[2] * r[1]
                    J[:, 1, k] = z[2] * r[0] - z[0] * r[2]
                    J[:, 2, k] = z[0] * r[1] - z[1] * r[0]
                    J[:, 3:, k] = z.T
        return T, None, J

    def fk_batch(self, Q):
        """Tool poses for many joint vectors: ``Q`` (N, n) -> (N, 4, 4)."""
        return self._forward(np.atleast_2d(Q))[0]

    def link_frames(self, Q):
        """Frames of every link of the chain (base first, tool last) for many
        joint vectors: ``Q`` (N, n) -> (N, S + 1, 4, 4), S = number of segments.
        Segment order is ``chain.segments``; used for collision checks."""
        return self._forward(np.atleast_2d(Q), frames=True)[1]

    def jacobian_batch(self, Q):
        """Geometric Jacobians (linear rows first) in the base frame at the tool:
        ``Q`` (N, n) -> (N, 6, n)."""
        return self._forward(np.atleast_2d(Q), jacobian=True)[2]

    # ------------------------------------------------------------------ IK
    def within_limits(self, Q, tol=1e-9):
        """Bool mask (N,) of joint vectors inside the joint limits."""
        Q = np.atleast_2d(Q)
        return np.all((Q >= self.lower - tol) & (Q <= self.upper + tol), axis=1)

    #: :meth:`ik_batch` solves at most this many targets at once (more: in
    #: pieces, 1.7x faster on a model's 160,000 corners than all at once)
    CHUNK = 16384

    def ik_batch(self, positions, seeds, axis=DOWN, tol=1e-7, axis_tol=1e-6, max_iter=60,
                 damping=1e-3, max_step=0.35):
        """Solve many IK problems at once.

        Parameters
        ----------
        positions : (N, 3) nozzle tip positions, m, base frame
        seeds : (N, n) or (n,) starting joint vectors
        axis : (3,) or (N, 3) wanted nozzle direction, base frame (default down)
        tol : position tolerance, m;  axis_tol : direction tolerance, rad

        Returns
        -------
        Q : (N, n) joint vectors (where ``ok`` is False: the last iterate)
        ok : (N,) bool, converged within tolerance and inside the joint limits
        err : (N,) position error, m
        """
        P = np.atleast_2d(np.asarray(positions, dtype=float))
        N = P.shape[0]
        if N > self.CHUNK:               # in pieces that stay in the cache (each row is solved on its own)
            seeds = np.asarray(seeds, dtype=float)
            axis = np.asarray(axis, dtype=float)
            part = lambda x, i: x[i:i + self.CHUNK] if x.ndim == 2 and len(x) == N else x
            out = [self.ik_batch(P[i:i + self.CHUNK], part(seeds, i), part(axis, i), tol, axis_tol, max_iter,
                                 damping, max_step) for i in range(0, N, self.CHUNK)]
            return tuple(np.concatenate(x) for x in zip(*out))
        if N == 1:                       # one target (a path's key points, a joint move): plain floats
            q, ok1, err1 = self._ik_one(P[0], np.reshape(seeds, -1), np.reshape(axis, -1)[:3], tol, axis_tol,
                                        max_iter, damping, max_step)
            return np.array([q]), np.array([ok1]), np.array([err1])
        Q = np.array(np.broadcast_to(seeds, (N, self.dof)), dtype=float)
        D = np.broadcast_to(np.asarray(axis, dtype=float), (N, 3))
        D = D / np.linalg.norm(D, axis=1, keepdims=True)
        # an orthonormal pair (u, v) perpendicular to each wanted direction
        helper = np.where(np.abs(D[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        U = _cross(D, np.broadcast_to(helper, D.shape))
        U /= np.linalg.norm(U, axis=1, keepdims=True)
        V = _cross(D, U)
        H = None if self.trail is None else trail_targets(P, D, U)
        rows = 5 if H is None else 6
        finite_limits = np.isfinite(self.lower) | np.isfinite(self.upper)
        Q = np.clip(Q, self.lower, self.upper)
        ok = np.zeros(N, dtype=bool)
        err = np.full(N, np.inf)
        active = np.arange(N)
        lam2 = damping ** 2
        for _ in range(max_iter + 1):
            T, _, J = self._forward(Q[active], jacobian=True)
            a = T[:, :3, :3] @ self.tool_axis
            ep = P[active] - T[:, :3, 3]
            d = D[active]
            c = _cross(a, d)
            sin_t = np.linalg.norm(c, axis=1)
            cos_t = np.einsum("ij,ij->i", a, d)
            ang = np.arctan2(sin_t, cos_t)
            eo = np.where(sin_t[:, None] > 1e-12, c * (ang / np.maximum(sin_t, 1e-300))[:, None],
                          np.where(cos_t[:, None] > 0, 0.0, U[active] * np.pi))
            perr = np.linalg.norm(ep, axis=1)
            err[active] = perr
            done = (perr <= tol) & (ang <= axis_tol)
            if H is not None:
                # the turn about the wanted axis that brings the trail onto its target
                b = T[:, :3, :3] @ self.trail
                b = b - np.einsum("ij,ij->i", b, d)[:, None] * d
                h = H[active]
                turn = np.arctan2(np.einsum("ij,ij->i", _cross(b, h), d), np.einsum("ij,ij->i", b, h))
                done &= np.abs(turn) <= axis_tol
            ok[active[done]] = True
            keep = ~done
            if not keep.any() or _ == max_iter:
                break
            active, ep, eo, J = active[keep], ep[keep], eo[keep], J[keep]
            u, v = U[active], V[active]
            A = [J[:, :3, :], np.einsum("ij,ijk->ik", u, J[:, 3:, :])[:, None, :],
                 np.einsum("ij,ijk->ik", v, J[:, 3:, :])[:, None, :]]
            e = [ep, np.einsum("ij,ij->i", u, eo)[:, None], np.einsum("ij,ij->i", v, eo)[:, None]]
            if H is not None:
                A.append(np.einsum("ij,ijk->ik", D[active], J[:, 3:, :])[:, None, :])
                e.append(turn[keep][:, None])
            A = np.concatenate(A, axis=1)                                                    # (M,rows,n)
            e = np.concatenate(e, axis=1)                                                    # (M,rows)
            AAt = A @ A.transpose(0, 2, 1) + lam2 * np.eye(rows)
            dq = np.einsum("ikj,ik->ij", A, np.linalg.solve(AAt, e[:, :, None])[:, :, 0])
            big = np.max(np.abs(dq), axis=1)
            dq *= np.minimum(1.0, max_step / np.maximum(big, 1e-300))[:, None]
            Qa = Q[active] + dq
            if finite_limits.any():
                Qa = np.clip(Qa, self.lower, self.upper)
            Q[active] = Qa
        ok &= self.within_limits(Q)
        return Q, ok, err

    def _fk_one(self, qs):
        """Tool position, tool rotation (row-major, 9 floats) and the
        Jacobian's columns (linear (3,), angular (3,)) at one joint vector,
        in plain floats: :meth:`_forward` for one pose without numpy's
        per-call cost (what a path's key points, solved one by one, pay)."""
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
        px = py = pz = 0.0
        cols = []
        for (o00, o01, o02, o10, o11, o12, o20, o21, o22), (ox, oy, oz), qi, axis, zaxis in self._plan_py:
            px, py, pz = (r00 * ox + r01 * oy + r02 * oz + px, r10 * ox + r11 * oy + r12 * oz + py,
                          r20 * ox + r21 * oy + r22 * oz + pz)
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = (
                r00 * o00 + r01 * o10 + r02 * o20, r00 * o01 + r01 * o11 + r02 * o21, r00 * o02 + r01 * o12 + r02 * o22,
                r10 * o00 + r11 * o10 + r12 * o20, r10 * o01 + r11 * o11 + r12 * o21, r10 * o02 + r11 * o12 + r12 * o22,
                r20 * o00 + r21 * o10 + r22 * o20, r20 * o01 + r21 * o11 + r22 * o21, r20 * o02 + r21 * o12 + r22 * o22)
            if qi is None:
                continue
            q = qs[qi]
            ax, ay, az = axis
            zx = r00 * ax + r01 * ay + r02 * az
            zy = r10 * ax + r11 * ay + r12 * az
            zz = r20 * ax + r21 * ay + r22 * az
            cols.append((zaxis, zx, zy, zz, px, py, pz))
            if zaxis is None:          # prismatic
                px, py, pz = px + zx * q, py + zy * q, pz + zz * q
            elif zaxis:                # rotation about local z: mix columns 0 and 1
                c, s = math.cos(q), math.sin(q)
                r00, r01 = c * r00 + s * r01, c * r01 - s * r00
                r10, r11 = c * r10 + s * r11, c * r11 - s * r10
                r20, r21 = c * r20 + s * r21, c * r21 - s * r20
            else:
                G = _rodrigues(np.asarray(axis), np.array([q]))[0]
                (g00, g01, g02), (g10, g11, g12), (g20, g21, g22) = G.tolist()
                r00, r01, r02, r10, r11, r12, r20, r21, r22 = (
                    r00 * g00 + r01 * g10 + r02 * g20, r00 * g01 + r01 * g11 + r02 * g21,
                    r00 * g02 + r01 * g12 + r02 * g22, r10 * g00 + r11 * g10 + r12 * g20,
                    r10 * g01 + r11 * g11 + r12 * g21, r10 * g02 + r11 * g12 + r12 * g22,
                    r20 * g00 + r21 * g10 + r22 * g20, r20 * g01 + r21 * g11 + r22 * g21,
                    r20 * g02 + r21 * g12 + r22 * g22)
        jac = []
        for zaxis, zx, zy, zz, qx, qy, qz in cols:
            if zaxis is None:
                jac.append((zx, zy, zz, 0.0, 0.0, 0.0))
            else:
                rx, ry, rz = px - qx, py - qy, pz - qz
                jac.append((zy * rz - zz * ry, zz * rx - zx * rz, zx * ry - zy * rx, zx, zy, zz))
        return (px, py, pz), (r00, r01, r02, r10, r11, r12, r20, r21, r22), jac

    def _ik_one(self, target, seed, axis, tol, axis_tol, max_iter, damping, max_step):
        """:meth:`ik_batch` for one target, the same iteration in plain
        floats (numpy only for the 5 x 5 solve): (q (n,), ok, err)."""
        n = self.dof
        lo, hi = self._lower_py, self._upper_py
        tx, ty, tz = (float(v) for v in target)
        dx, dy, dz = (float(v) for v in axis)
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx / norm, dy / norm, dz / norm
        hx, hy, hz = (1.0, 0.0, 0.0) if abs(dx) < 0.9 else (0.0, 1.0, 0.0)
        ux, uy, uz = dy * hz - dz * hy, dz * hx - dx * hz, dx * hy - dy * hx
        norm = math.sqrt(ux * ux + uy * uy + uz * uz)
        ux, uy, uz = ux / norm, uy / norm, uz / norm
        vx, vy, vz = dy * uz - dz * uy, dz * ux - dx * uz, dx * uy - dy * ux
        q = [min(max(float(v), lo[i]), hi[i]) for i, v in enumerate(seed)]
        finite = any(math.isfinite(a) or math.isfinite(b) for a, b in zip(lo, hi))
        tax, tay, taz = (float(v) for v in self.tool_axis)
        trail = self.trail is not None
        if trail:
            bx0, by0, bz0 = (float(v) for v in self.trail)
            (hx, hy, hz), = trail_targets(np.array([[tx, ty, tz]]), np.array([[dx, dy, dz]]),
                                          np.array([[ux, uy, uz]])).tolist()
        lam2 = damping ** 2
        ok, err = False, math.inf
        eye = np.eye(6 if trail else 5) * lam2
        for it in range(max_iter + 1):
            (px, py, pz), (r00, r01, r02, r10, r11, r12, r20, r21, r22), jac = self._fk_one(q)
            ax, ay, az = r00 * tax + r01 * tay + r02 * taz, r10 * tax + r11 * tay + r12 * taz, \
                r20 * tax + r21 * tay + r22 * taz
            ex, ey, ez = tx - px, ty - py, tz - pz
            cx, cy, cz = ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx
            sin_t = math.sqrt(cx * cx + cy * cy + cz * cz)
            cos_t = ax * dx + ay * dy + az * dz
            ang = math.atan2(sin_t, cos_t)
            if sin_t > 1e-12:
                f = ang / max(sin_t, 1e-300)
                ox, oy, oz = cx * f, cy * f, cz * f
            elif cos_t > 0:
                ox = oy = oz = 0.0
            else:
                ox, oy, oz = ux * math.pi, uy * math.pi, uz * math.pi
            err = math.sqrt(ex * ex + ey * ey + ez * ez)
            rows = [[c[0] for c in jac], [c[1] for c in jac], [c[2] for c in jac],
                    [ux * c[3] + uy * c[4] + uz * c[5] for c in jac],
                    [vx * c[3] + vy * c[4] + vz * c[5] for c in jac]]
            e = [ex, ey, ez, ux * ox + uy * oy + uz * oz, vx * ox + vy * oy + vz * oz]
            turn = 0.0
            if trail:                  # as in ik_batch: the turn about the axis onto the trail's target
                bx, by, bz = r00 * bx0 + r01 * by0 + r02 * bz0, r10 * bx0 + r11 * by0 + r12 * bz0, \
                    r20 * bx0 + r21 * by0 + r22 * bz0
                k = bx * dx + by * dy + bz * dz
                bx, by, bz = bx - k * dx, by - k * dy, bz - k * dz
                turn = math.atan2((by * hz - bz * hy) * dx + (bz * hx - bx * hz) * dy + (bx * hy - by * hx) * dz,
                                  bx * hx + by * hy + bz * hz)
                rows.append([dx * c[3] + dy * c[4] + dz * c[5] for c in jac])
                e.append(turn)
            if err <= tol and ang <= axis_tol and abs(turn) <= axis_tol:
                ok = True
                break
            if it == max_iter:
                break
            A = np.array(rows)
            dq = (A.T @ np.linalg.solve(A @ A.T + eye, np.array(e))).tolist()
            big = max(abs(v) for v in dq)
            scale = min(1.0, max_step / max(big, 1e-300))
            q = [q[i] + dq[i] * scale for i in range(n)]
            if finite:
                q = [min(max(v, lo[i]), hi[i]) for i, v in enumerate(q)]
        ok = ok and all(lo[i] - 1e-9 <= v <= hi[i] + 1e-9 for i, v in enumerate(q))
        return np.array(q), ok, err

    def task_jacobian(self, q, axis=DOWN):
        """The IK's task rows at joints ``q`` for a nozzle along ``axis``
        (base frame): the nozzle's velocity (3 rows), the tilt of its axis
        about the two directions perpendicular to ``axis`` (2), and with a
        ``trail`` the turn about the axis (1) -> (5 or 6, n)."""
        T, _, J = self._forward(np.reshape(np.asarray(q, dtype=float), (1, -1)), jacobian=True)
        d = np.asarray(axis, dtype=float).reshape(3)
        d = d / np.linalg.norm(d)
        u = _cross(d[None], np.array([[1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0]]))[0]
        u /= np.linalg.norm(u)
        rows = [J[0, :3], u @ J[0, 3:], np.cross(d, u) @ J[0, 3:]]
        if self.trail is not None:
            rows.append(d @ J[0, 3:])
        return np.vstack(rows)

    def spare(self):
        """Whether the arm has joints to spare for its task (a self-motion)."""
        return self.dof > (5 if self.trail is None else 6)

    def _toward_rest(self, position, q, axis, budget, kw):
        """``q`` (solving ``position``) moved along the self-motion towards
        :attr:`rest` by at most ``budget`` rad on any joint, the task solved
        again from there; ``q`` itself if that fails."""
        A = self.task_jacobian(q, axis)
        step = (np.eye(self.dof) - np.linalg.pinv(A, rcond=1e-6) @ A) @ (self.rest - q)
        big = float(np.max(np.abs(step)))
        if big < 1e-9:
            return q
        step *= min(1.0, budget / big)
        Q, ok, _ = self.ik_batch(np.reshape(position, (1, 3)), q + step, axis, **kw)
        return Q[0] if ok[0] else q

    def ik(self, position, seed, axis=DOWN, **kw):
        """One IK solve: joint vector (n,) that puts the nozzle tip at
        ``position`` (3,) pointing along ``axis``, starting from ``seed``.
        Raises :class:`UnreachableError` if no solution within the joint
        limits is found from that seed."""
        Q, ok, err = self.ik_batch(np.reshape(position, (1, 3)), np.asarray(seed, dtype=float), axis, **kw)
        if not ok[0]:
            p = np.reshape(position, 3)
            raise UnreachableError(
                "no joint configuration within limits puts the nozzle at (%.4f, %.4f, %.4f) m pointing "
                "(%.2f, %.2f, %.2f): closest reached %.4f m away" % (tuple(p) + tuple(np.ravel(axis)[:3]) + (err[0],)))
        return Q[0]

    def ik_path(self, positions, seed, axis=DOWN, key_spacing=0.02, max_joint_step=None, **kw):
        """IK along a densely sampled path, continuous from ``seed``.

        Key points at most ``key_spacing`` (m) apart are solved one after the
        other (each seeded by the previous one); every point is then refined at
        once from joint seeds interpolated between the keys.  An arm with joints
        to spare and a :attr:`rest` posture steps each key after the first along
        its self-motion towards that posture, by at most :data:`POSTURE_RAD_PER_M`
        times the path's length from the key before (the points between follow
        the keys: the refinement's least-norm steps keep their self-motion).  A point whose
        joints move more than ``max_joint_step`` (rad; default: 10x the path
        step over the reach, at least 0.05) from its neighbour counts as a
        discontinuity and is not ok.

        Returns ``Q`` (N, n) and ``ok`` (N,): points after the first failure
        are not ok either (the arm cannot get past it without re-planning).
        """
        P = np.atleast_2d(np.asarray(positions, dtype=float))
        N = P.shape[0]
        seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        nkeys = max(1, int(np.ceil(s[-1] / key_spacing)))
        keys = np.unique(np.searchsorted(s, np.linspace(0.0, s[-1], nkeys + 1)).clip(0, N - 1))
        keys[0], keys[-1] = 0, N - 1
        keys = np.unique(keys)
        D = np.broadcast_to(np.asarray(axis, dtype=float), (N, 3))
        Qk = np.empty((len(keys), self.dof))
        q = np.asarray(seed, dtype=float)
        ok = np.zeros(N, dtype=bool)
        n_ok_keys = len(keys)
        posture = self.rest is not None and self.spare()
        for i, k in enumerate(keys):
            Qi, oki, _ = self.ik_batch(P[k:k + 1], q, D[k], **kw)
            if not oki[0]:
                n_ok_keys = i
                break
            q = Qi[0]
            if posture and i > 0:        # the path starts where the seed is; later keys turn towards rest
                q = self._toward_rest(P[k], q, D[k], POSTURE_RAD_PER_M * (s[k] - s[keys[i - 1]]), kw)
            Qk[i] = q
        if n_ok_keys == 0:
            return np.tile(np.asarray(seed, dtype=float), (N, 1)), ok
        last = keys[n_ok_keys - 1]
        good = slice(0, last + 1)
        seeds = np.empty((last + 1, self.dof))
        for j in range(self.dof):
            seeds[:, j] = np.interp(s[good], s[keys[:n_ok_keys]], Qk[:n_ok_keys, j])
        Q = np.tile(Qk[n_ok_keys - 1], (N, 1))
        Q[good], ok[good], _ = self.ik_batch(P[good], seeds, D[good], **kw)
        if max_joint_step is None:
            step = np.max(seg) if len(seg) else 0.0
            max_joint_step = max(0.05, 10.0 * step / 0.3)
        # the seed is only a starting guess: continuity is checked along the path
        jump = np.concatenate([[0.0], np.max(np.abs(np.diff(Q, axis=0)), axis=1)])
        ok &= jump <= max_joint_step + 1e-12
        if n_ok_keys < len(keys) or not ok.all():
            first_bad = int(np.argmin(ok)) if not ok.all() else last + 1
            ok[first_bad:] = False
        return Q, ok


def trail_targets(P, D, U):
    """Where an offset head's ``trail`` should point at nozzle positions ``P``
    (N, 3) with nozzle axes ``D`` (N, 3, unit), base frame: the horizontal
    direction from the nozzle towards the base frame's z axis, made
    perpendicular to the nozzle axis -> (N, 3) unit vectors.  It turns
    smoothly with the nozzle (by the nozzle's move over its distance from
    the axis: 0.2 degrees a millimetre 0.3 m out).  On the axis itself, or
    with a nozzle axis horizontal and pointing at it, ``U`` (N, 3), any
    direction perpendicular to the axis."""
    H = np.zeros((len(P), 3))
    H[:, 0], H[:, 1] = -P[:, 0], -P[:, 1]
    H -= np.einsum("ij,ij->i", H, D)[:, None] * D
    norm = np.linalg.norm(H, axis=1)
    small = norm < 1e-9
    H[~small] /= norm[~small, None]
    H[small] = U[small]
    return H


_SHARED = {}


def shared_arm_kinematics(arm):
    """:func:`ambots.model.arm_kinematics` of ``arm`` (an ArmInstance or an
    ArmProfile), built once per arm model and shared (a build runs xacro,
    0.1-0.2 s; a job's planners and reach checks ask for it a dozen times).
    The URDF comes from the profile's files (``model`` and ``path``), so the
    key is those files as they are now (their modification times) and the
    chain's ends.  Callers must not modify the object."""
    import os

    from ambots.model import arm_kinematics
    profile = getattr(arm, "profile", arm)

    def mtime(path):
        try:
            return os.stat(path).st_mtime_ns
        except (OSError, TypeError, ValueError):
            return None

    key = (profile.model, profile.path, mtime(profile.model), mtime(profile.path), profile.base_link,
           profile.tool_link)
    kin = _SHARED.get(key)
    if kin is None:
        kin = _SHARED[key] = arm_kinematics(arm)
    return kin
