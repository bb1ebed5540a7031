"""Where arms stand and what they reach: transforms between the world frame
and an arm's base frame, and reachability of the print bed.

Units: metres.  Arrays of points are (N, 3).
"""
import numpy as np

from ambots.kinematics import DOWN

__all__ = ["world_to_base", "base_to_world", "bed_points", "bed_reachability", "down_in_base"]


def world_to_base(arm, points):
    """World points (N, 3) -> the arm's base frame (N, 3)."""
    T = arm.base_pose
    return (np.asarray(points, dtype=float) - T[:3, 3]) @ T[:3, :3]


def base_to_world(arm, points):
    """Points in the arm's base frame (N, 3) -> world (N, 3)."""
    T = arm.base_pose
    return np.asarray(points, dtype=float) @ T[:3, :3].T + T[:3, 3]


def down_in_base(arm):
    """World 'down' (nozzle pointing at the bed) expressed in the arm's base frame."""
    return arm.base_pose[:3, :3].T @ DOWN


def bed_points(cell, n=5, heights=(0.0, 0.15)):
    """A grid of n x n points over the bed's top surface, repeated at each
    height above it: (n * n * len(heights), 3) world points."""
    sx, sy, _ = cell.bed.size
    u, v = np.meshgrid(np.linspace(-sx / 2, sx / 2, n), np.linspace(-sy / 2, sy / 2, n), indexing="ij")
    pts = []
    for h in heights:
        local = np.stack([u.ravel(), v.ravel(), np.full(u.size, h)], axis=1)
        T = cell.bed.pose
        pts.append(local @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(pts)


def bed_reachability(cell, arm, kin, points=None):
    """Bool mask (N,): which bed points (default :func:`bed_points`) the arm's
    nozzle reaches pointing down, solved from the arm's home configuration."""
    pts = bed_points(cell) if points is None else np.asarray(points, dtype=float)
    local = world_to_base(arm, pts)
    _, ok, _ = kin.ik_batch(local, np.asarray(arm.profile.home), down_in_base(arm))
    return ok
