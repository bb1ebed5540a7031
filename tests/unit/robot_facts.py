"""Published kinematics and limits, copied from the project's shared
ROBOT_FACTS.md (manufacturers' data) so that tests check the models against
numbers that do not come from the models themselves.  Metres, radians."""
import math

# UR10 (CB3), standard DH (d, a, alpha) per joint; joint i rotates about z(i-1)
UR10_DH = [
    (0.1273, 0.0, math.pi / 2),
    (0.0, -0.612, 0.0),
    (0.0, -0.5723, 0.0),
    (0.163941, 0.0, math.pi / 2),
    (0.1157, 0.0, -math.pi / 2),
    (0.0922, 0.0, 0.0),
]
UR10_FLANGE_AT_ZERO = (-1.1843, -0.256141, 0.0116)
UR10_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
               "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
UR10_MAX_SPEED = [2.0944, 2.0944, 3.1416, 3.1416, 3.1416, 3.1416]
UR10_RANGE = 2 * math.pi   # +-2 pi every joint (the ROS description narrows the elbow to +-pi)

# Kinova Gen3 6 DOF: parent -> child (xyz, rpy); every joint axis is the child's z
KINOVA_ORIGINS = [
    ((0, 0, 0.15643), (-3.1416, 0, 0)),
    ((0, 0.005375, -0.12838), (1.5708, 0, 0)),
    ((0, -0.41, 0), (3.1416, 0, 0)),
    ((0, 0.20843, -0.006375), (1.5708, 0, 0)),
    ((0, -0.00017505, -0.10593), (-1.5708, 0, 0)),
    ((0, 0.10593, -0.00017505), (1.5708, 0, 0)),
]
KINOVA_EE = ((0, 0, -0.061525), (3.1416, 0, -3.1416))   # bracelet_link -> end_effector_link
KINOVA_JOINTS = ["joint_%d" % i for i in range(1, 7)]
KINOVA_LIMITS = [None, (-2.24, 2.24), (-2.57, 2.57), None, (-2.09, 2.09), None]   # None: continuous
KINOVA_MAX_SPEED = [1.3963, 1.3963, 1.3963, 1.2218, 1.2218, 1.2218]

# Franka Emika Panda, 7 DOF: modified (Craig) DH, (a_(i-1), alpha_(i-1), d_i) per joint;
# T(i-1, i) = RotX(alpha_(i-1)) TransX(a_(i-1)) RotZ(q_i) TransZ(d_i)
PANDA_MDH = [
    (0.0, 0.0, 0.333),
    (0.0, -math.pi / 2, 0.0),
    (0.0, math.pi / 2, 0.316),
    (0.0825, math.pi / 2, 0.0),
    (-0.0825, -math.pi / 2, 0.384),
    (0.0, math.pi / 2, 0.0),
    (0.088, math.pi / 2, 0.0),
]
PANDA_FLANGE = (0.0, 0.0, 0.107)   # (a, alpha, d) of the fixed flange row
PANDA_JOINTS = ["panda_joint%d" % i for i in range(1, 8)]
PANDA_LIMITS = [(-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698),
                (-2.8973, 2.8973), (-0.0175, 3.7525), (-2.8973, 2.8973)]
PANDA_MAX_SPEED = [2.1750, 2.1750, 2.1750, 2.1750, 2.6100, 2.6100, 2.6100]
PANDA_REACH = 0.855

# ---------------------------------------------------------------- body envelopes
# ROBOT_FACTS "Body envelopes" (the manufacturers' collision meshes, posed by their own
# kinematics), mm -> m.  Per table row: the radius about the link's axis (the line between the
# two joint centres it connects; the largest value of a range, along the whole link unless
# the row says where), and how far the housings reach beyond the joint ("up to").
UR10_ENVELOPE = {
    "base": (0.105, 0.030),             # 105 (ball-like); housings 30
    "shoulder": (0.101, 0.082),         # 76-101; up to 82
    "upper_arm": (0.054, 0.102),        # tube 54 ...
    "upper_arm_housings": 0.103,        # ... 103 at the shoulder and elbow housings; up to 102
    "forearm": (0.044, 0.077),          # tube 44 ...
    "forearm_elbow_housing": 0.076,     # ... 76 at the elbow housing; up to 77
    "wrist_1": (0.076, 0.035),          # wrist 1 and wrist 2: 68-76; up to 35
    "wrist_2": (0.076, 0.035),
    "wrist_3": (0.047, 0.002),          # 47; 2
}
KINOVA_ENVELOPE = {
    "base": (0.054, 0.030),             # 46-54; 30
    "shoulder": (0.057, 0.053),         # shoulder, bicep, forearm: 55-57, 46-55, 39-54; up to 53
    "bicep": (0.055, 0.053),
    "forearm": (0.054, 0.053),
    "spherical_wrist_1": (0.046, 0.043),   # spherical wrists 1 and 2: 37-46; up to 43
    "spherical_wrist_2": (0.046, 0.043),
    "bracelet": (0.050, 0.015),         # 50; 15
}
# Where the joint centres are (the table does not say; these are the models' choices, given
# here so that the envelope test builds the envelopes from these numbers and the published
# kinematics, not from the models' bodies).  UR10: J1 at d1 above the floor; J2 and J3 where
# the upper-arm tube sits along their axes, the forearm tube's ends along the J3 and J4 axes;
# J5 and J6 where the wrist axes cross (DH origins o4 and o5).  Kinova: each joint's origin.
UR10_UPPER_ARM_TUBE_Z = 0.176    # along the J2/J3 axes from the DH origins (urdf/ur10.xacro)
UR10_FOREARM_TUBE_Z = 0.049      # along the J3/J4 axes (the manufacturer's elbow offset)
# the print head (arm profiles' tool.head): every body stays this far behind the nozzle tip
HEAD_TIP_GAP = 0.005
