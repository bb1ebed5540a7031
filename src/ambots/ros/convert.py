"""numpy <-> ROS message conversions."""
import numpy as np
from geometry_msgs.msg import TransformStamped


def quaternion_from_matrix(R):
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix."""
    R = np.asarray(R, dtype=float)
    w = np.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = np.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2
    z = np.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    return x, y, z, w


def transform_msg(parent, child, T, stamp=None):
    """TransformStamped parent -> child from a 4x4 pose."""
    import rospy
    t = TransformStamped()
    t.header.stamp = stamp or rospy.Time.now()
    t.header.frame_id, t.child_frame_id = parent, child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = map(float, T[:3, 3])
    q = quaternion_from_matrix(T[:3, :3])
    t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w = q
    return t
