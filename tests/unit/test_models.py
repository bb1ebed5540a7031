"""The arm models agree with the manufacturers' published kinematics and limits."""
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import robot_facts as F
from ambots import data_path
from ambots.config import load_arm_profile, pose_matrix
from ambots.kinematics import ArmKinematics, chain_from_urdf
from ambots.model import arm_urdf

RNG = np.random.default_rng(20261121)


def rpy_xyz(xyz, rpy):
    r, p, y = rpy
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = xyz
    return T


def rotz(q):
    T = np.eye(4)
    T[:2, :2] = [[np.cos(q), -np.sin(q)], [np.sin(q), np.cos(q)]]
    return T


def dh_fk(q):
    """Independent standard-DH forward kinematics of the UR10 (flange = frame 6)."""
    T = np.eye(4)
    for qi, (d, a, alpha) in zip(q, F.UR10_DH):
        A = np.array([[np.cos(qi), -np.sin(qi) * np.cos(alpha), np.sin(qi) * np.sin(alpha), a * np.cos(qi)],
                      [np.sin(qi), np.cos(qi) * np.cos(alpha), -np.cos(qi) * np.sin(alpha), a * np.sin(qi)],
                      [0, np.sin(alpha), np.cos(alpha), d],
                      [0, 0, 0, 1]])
        T = T @ A
    return T


def kinova_fk(q):
    """Independent joint-origin chain of the Kinova Gen3 6 DOF (to end_effector_link)."""
    T = np.eye(4)
    for qi, (xyz, rpy) in zip(q, F.KINOVA_ORIGINS):
        T = T @ rpy_xyz(xyz, rpy) @ rotz(qi)
    return T @ rpy_xyz(*F.KINOVA_EE)


def flange_kin(profile_name):
    prof = load_arm_profile("config/arms/%s.yaml" % profile_name)
    return prof, ArmKinematics.from_urdf(arm_urdf(prof), tip="flange")


def random_q(kin, n):
    lo = np.where(np.isfinite(kin.lower), kin.lower, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, np.pi)
    return RNG.uniform(lo, hi, (n, kin.dof))


def test_ur10_flange_at_zero_is_the_published_check_value():
    _, kin = flange_kin("ur10")
    np.testing.assert_allclose(kin.fk(np.zeros(6))[:3, 3], F.UR10_FLANGE_AT_ZERO, atol=1e-6)
    np.testing.assert_allclose(kin.fk_batch(np.zeros((1, 6)))[0, :3, 3], F.UR10_FLANGE_AT_ZERO, atol=1e-6)


@pytest.mark.parametrize("name, reference", [("ur10", dh_fk), ("kinova_gen3", kinova_fk)])
def test_flange_pose_agrees_with_published_kinematics_at_200_random_configurations(name, reference):
    _, kin = flange_kin(name)
    Q = random_q(kin, 200)
    expected = np.stack([reference(q) for q in Q])
    np.testing.assert_allclose(kin.fk_batch(Q), expected, atol=1e-6)        # numpy
    np.testing.assert_allclose(np.stack([kin.fk(q) for q in Q]), expected, atol=1e-6)   # KDL


@pytest.mark.parametrize("name, joints, speeds", [("ur10", F.UR10_JOINTS, F.UR10_MAX_SPEED),
                                                  ("kinova_gen3", F.KINOVA_JOINTS, F.KINOVA_MAX_SPEED)])
def test_joint_names_and_speed_limits_are_the_drivers_and_manufacturers(name, joints, speeds):
    prof, kin = flange_kin(name)
    assert kin.joint_names == joints
    np.testing.assert_allclose(kin.chain.velocity, speeds, atol=1e-4)
    assert list(prof.driver_joint_names) == joints


def test_position_limits():
    _, ur = flange_kin("ur10")
    assert ur.lower[2] == pytest.approx(-np.pi, abs=1e-4) and ur.upper[2] == pytest.approx(np.pi, abs=1e-4)
    for i in (0, 1, 3, 4, 5):
        assert ur.lower[i] == pytest.approx(-F.UR10_RANGE, abs=1e-4)
        assert ur.upper[i] == pytest.approx(F.UR10_RANGE, abs=1e-4)
    _, kin = flange_kin("kinova_gen3")
    for i, lim in enumerate(F.KINOVA_LIMITS):
        if lim is None:
            assert np.isinf(kin.lower[i]) and np.isinf(kin.upper[i]), "joint_%d is continuous" % (i + 1)
        else:
            assert (kin.lower[i], kin.upper[i]) == pytest.approx(lim, abs=1e-9)


@pytest.mark.parametrize("name", ["ur10", "kinova_gen3", "panda"])
def test_nozzle_is_the_tool_offset_from_the_flange(name):
    prof = load_arm_profile("config/arms/%s.yaml" % name)
    urdf = arm_urdf(prof)
    flange = ArmKinematics.from_urdf(urdf, tip="flange")
    nozzle = ArmKinematics.from_urdf(urdf, tip="nozzle")
    Q = random_q(flange, 20)
    tool = pose_matrix(prof.tool_xyz, prof.tool_rpy)
    N, F = nozzle.fk_batch(Q), flange.fk_batch(Q)
    np.testing.assert_allclose(N, F @ tool, atol=1e-12)
    # the trail the IK keeps towards the base: from the nozzle to the flange's
    # origin, across the nozzle axis (here 100 mm off it, 200 mm along it)
    back = np.einsum("nji,nj->ni", N[:, :3, :3], F[:, :3, 3] - N[:, :3, 3])     # in the nozzle frame
    np.testing.assert_allclose(back, np.broadcast_to([-0.10, 0.0, -0.20], back.shape), atol=1e-12)
    np.testing.assert_allclose(prof.tool_trail, [-1.0, 0.0, 0.0], atol=1e-12)
    assert prof.tool_turn == "toward_base"


@pytest.mark.parametrize("xacro_file, n_joints", [("ur10.xacro", 6), ("kinova_gen3_6dof.xacro", 6),
                                                    ("panda.xacro", 7)])
def test_xacro_processed_alone_yields_one_arm_of_primitives(tmp_path, xacro_file, n_joints):
    xacro_bin = os.path.join(os.path.dirname(sys.executable), "xacro")
    out = subprocess.run([xacro_bin, data_path("urdf", xacro_file)], cwd=tmp_path,
                         capture_output=True, text=True, check=True).stdout
    robot = ET.fromstring(out)
    links = {l.get("name") for l in robot.iter("link")}
    assert {"base_link", "flange", "nozzle"} <= links
    movable = [j for j in robot.iter("joint") if j.get("type") != "fixed"]
    assert len(movable) == n_joints
    assert not list(robot.iter("mesh")), "no meshes: primitives only"
    shapes = [g[0].tag for g in robot.iter("geometry")]
    assert shapes and set(shapes) <= {"cylinder", "box", "sphere"}
    chain_from_urdf(out, "base_link", "nozzle")   # one connected chain


def test_prefix_applies_to_every_link_and_joint():
    prof = load_arm_profile("config/arms/ur10.yaml")
    robot = ET.fromstring(arm_urdf(prof, "left/"))
    names = [e.get("name") for e in robot if e.tag in ("link", "joint")]
    assert names and all(n.startswith("left/") for n in names)
