"""Kinematics of one arm, from its URDF.

* :func:`chain_from_urdf` -- URDF string -> :class:`Chain` (a serial chain of
  fixed / revolute / continuous / prismatic segments), parsed with yourdfpy.
* :func:`kdl_chain` -- :class:`Chain` -> ``PyKDL.Chain`` (what kdl_parser does;
  kdl_parser_py is not packaged on Debian).
* :class:`ArmKinematics` -- forward kinematics (KDL for one configuration,
  vectorised numpy for many: ``(N, n)`` joint vectors -> ``(N, 4, 4)`` poses),
  geometric Jacobians, and inverse kinematics for a nozzle *position* plus a
  nozzle *axis direction* (usually straight down), leaving the rotation about
  the nozzle axis free.  IK is seeded, respects joint limits and reports
  failure instead of returning garbage.

The IK is a damped least-squares Newton iteration on a 5-row task (3 position
rows, 2 rows for the tilt of the nozzle axis), run on many targets at once.
:meth:`ArmKinematics.ik_path` solves a densely sampled toolpath by solving
sparse key points one after the other (each seeded by the previous one), then
refining every point at once from seeds interpolated between the keys.

Units: metres and radians.  All poses are in the arm's base frame.
"""
import io
from typing import List, NamedTuple, Optional

import numpy as np

from ambots.errors import KinematicsError, UnreachableError

__all__ = ["Segment", "Chain", "chain_from_urdf", "kdl_chain", "ArmKinematics", "DOWN"]

#: nozzle pointing straight down in a base frame whose z axis is up
DOWN = np.array([0.0, 0.0, -1.0])


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
    """

    def __init__(self, chain, tool_axis=(0.0, 0.0, 1.0)):
        if chain.dof == 0:
            raise KinematicsError("chain %s -> %s has no movable joint" % (chain.base, chain.tip))
        self.chain = chain
        self.tool_axis = np.asarray(tool_axis, dtype=float)
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
        self._kdl = None

    @classmethod
    def from_urdf(cls, urdf_xml, base="base_link", tip="nozzle", prefix="", tool_axis=(0.0, 0.0, 1.0)):
        """Build from a URDF string; ``prefix`` is prepended to ``base`` and ``tip``."""
        return cls(chain_from_urdf(urdf_xml, prefix + base, prefix + tip), tool_axis)

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
    def _forward(self, Q, frames=False, jacobian=False):
        Q = np.asarray(Q, dtype=float)
        N = Q.shape[0]
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
        Q = np.array(np.broadcast_to(seeds, (N, self.dof)), dtype=float)
        D = np.broadcast_to(np.asarray(axis, dtype=float), (N, 3))
        D = D / np.linalg.norm(D, axis=1, keepdims=True)
        # an orthonormal pair (u, v) perpendicular to each wanted direction
        helper = np.where(np.abs(D[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        U = _cross(D, np.broadcast_to(helper, D.shape))
        U /= np.linalg.norm(U, axis=1, keepdims=True)
        V = _cross(D, U)
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
            ok[active[done]] = True
            keep = ~done
            if not keep.any() or _ == max_iter:
                break
            active, ep, eo, J = active[keep], ep[keep], eo[keep], J[keep]
            u, v = U[active], V[active]
            A = np.concatenate([J[:, :3, :],
                                np.einsum("ij,ijk->ik", u, J[:, 3:, :])[:, None, :],
                                np.einsum("ij,ijk->ik", v, J[:, 3:, :])[:, None, :]], axis=1)  # (M,5,n)
            e = np.concatenate([ep, np.einsum("ij,ij->i", u, eo)[:, None],
                                np.einsum("ij,ij->i", v, eo)[:, None]], axis=1)              # (M,5)
            AAt = A @ A.transpose(0, 2, 1) + lam2 * np.eye(5)
            dq = np.einsum("ikj,ik->ij", A, np.linalg.solve(AAt, e[:, :, None])[:, :, 0])
            big = np.max(np.abs(dq), axis=1)
            dq *= np.minimum(1.0, max_step / np.maximum(big, 1e-300))[:, None]
            Qa = Q[active] + dq
            if finite_limits.any():
                Qa = np.clip(Qa, self.lower, self.upper)
            Q[active] = Qa
        ok &= self.within_limits(Q)
        return Q, ok, err

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
        once from joint seeds interpolated between the keys.  A point whose
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
        for i, k in enumerate(keys):
            Qi, oki, _ = self.ik_batch(P[k:k + 1], q, D[k], **kw)
            if not oki[0]:
                n_ok_keys = i
                break
            q = Qk[i] = Qi[0]
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
