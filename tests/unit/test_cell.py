"""Arm profiles and cells: loading, checking, and the generated descriptions."""
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml

from ambots import data_path
from ambots.config import default_cell_path, load_arm_profile, load_cell
from ambots.errors import ConfigError
from ambots.kinematics import chain_from_urdf
from ambots.model import arm_kinematics, cell_urdf
from ambots.rviz import rviz_config
from ambots.workspace import base_to_world, bed_reachability, world_to_base


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


def write_cell(tmp_path, mutate):
    with open(default_cell_path()) as f:
        data = yaml.safe_load(f)
    for arm in data["arms"]:
        arm["profile"] = data_path(arm["profile"])
    mutate(data)
    path = tmp_path / "my cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_default_cell_has_two_arms_facing_each_other_across_the_bed(cell):
    assert [a.name for a in cell.arms] == ["kinova", "ur10"]
    # the original's robot ids and inbox topics
    assert [a.id for a in cell.arms] == [0, 1]
    assert [a.inbox for a in cell.arms] == ["/ambots/kinova_topic", "/ambots/ur_topic"]
    kinova, ur10 = cell.arms
    assert ur10.base_xyz[0] == pytest.approx(1.5)
    assert abs(ur10.base_rpy[2]) == pytest.approx(np.pi)       # turned to face the Kinova
    assert kinova.base_xyz[0] < cell.bed.xyz[0] < ur10.base_xyz[0]


def test_both_arms_reach_the_whole_bed_with_the_nozzle_down(cell):
    for arm in cell.arms:
        ok = bed_reachability(cell, arm, arm_kinematics(arm))
        assert ok.all(), "%s misses %d bed points" % (arm.name, (~ok).sum())


def test_each_home_pose_points_the_nozzle_down_over_the_bed(cell):
    for arm in cell.arms:
        T = arm.base_pose @ arm_kinematics(arm).fk(np.asarray(arm.profile.home))
        assert T[2, 2] == pytest.approx(-1.0, abs=1e-3), arm.name
        assert T[2, 3] > cell.bed.xyz[2] + 0.1


def test_world_base_transforms_are_inverse(cell):
    pts = np.random.default_rng(0).uniform(-1, 1, (20, 3))
    for arm in cell.arms:
        np.testing.assert_allclose(base_to_world(arm, world_to_base(arm, pts)), pts, atol=1e-12)


def test_cell_urdf_holds_world_bed_and_every_prefixed_arm(cell):
    urdf = cell_urdf(cell)
    robot = ET.fromstring(urdf)
    links = {l.get("name") for l in robot.iter("link")}
    assert {"world", "bed", "kinova/base_link", "kinova/nozzle", "ur10/base_link", "ur10/nozzle"} <= links
    for arm in cell.arms:   # the world -> nozzle chain is connected and agrees with base pose x FK
        chain = chain_from_urdf(urdf, "world", arm.frame("nozzle"))
        assert chain.joint_names == [arm.prefix + j for j in arm.profile.joint_names]
        from ambots.kinematics import ArmKinematics
        kin = ArmKinematics(chain)
        home = np.asarray(arm.profile.home)
        np.testing.assert_allclose(kin.fk(home), arm.base_pose @ arm_kinematics(arm).fk(home), atol=1e-9)


def test_shipped_rviz_config_is_what_the_generator_makes(cell):
    with open(data_path("config", "rviz", "kinova_ur10.rviz")) as f:
        assert f.read() == rviz_config(cell), "regenerate: python -m ambots cell --rviz config/rviz/kinova_ur10.rviz"
    displays = yaml.safe_load(rviz_config(cell))["Visualization Manager"]["Displays"]
    assert sorted(d["Robot Description"] for d in displays if d["Class"] == "rviz/RobotModel") == \
        ["/kinova/robot_description", "/ur10/robot_description"]


@pytest.mark.parametrize("mutate, field, message", [
    (lambda d: d["bed"].pop("size"), "bed.size", "missing field"),
    (lambda d: d["arms"][1]["base"].update(xyz=[0.1, 0.0, 0.0]), "arms", "overlap: 0.100 m apart"),
    (lambda d: d["arms"][1].update(profile="config/arms/no_such_arm.yaml"), "arms[1].profile", "not found"),
    (lambda d: d["arms"][1].update(id=0), "arms[1].id", "duplicate robot id 0"),
    (lambda d: d["arms"][1].update(id=1000), "arms[1].id", "1000 is the front end, 1001 the hub"),
    (lambda d: d["arms"][1].update(topic="/ambots/kinova_topic"), "arms[1].topic", "already the topic of arm 'kinova'"),
    (lambda d: d["arms"][1].update(topic="/ambots/communication_hub_topic"), "arms[1].topic", "hub"),
    (lambda d: d["arms"][1].update(topic="ur_topic"), "arms[1].topic", "a global ROS topic name"),
    (lambda d: d["arms"][0].update(name="Kinova Arm"), "arms[0].name", "lower-case"),
    (lambda d: d["arms"][0]["base"].update(rpy=[0, 0, "x"]), "arms[0].base.rpy", "3 finite numbers"),
    (lambda d: d.update(arms=[]), "arms", "non-empty list"),
])
def test_bad_cells_name_the_file_and_field(tmp_path, mutate, field, message):
    path = write_cell(tmp_path, mutate)
    with pytest.raises(ConfigError) as err:
        load_cell(path)
    assert err.value.field == field and message in str(err.value) and path in str(err.value)


def test_an_arm_without_a_topic_gets_the_default_inbox(tmp_path):
    cell = load_cell(write_cell(tmp_path, lambda d: d["arms"][0].pop("topic")))
    assert [a.inbox for a in cell.arms] == ["/kinova/firmware_topic", "/ambots/ur_topic"]


def test_unknown_arm_is_refused_by_name(cell):
    with pytest.raises(ConfigError, match="unknown arm 'panda'.*kinova, ur10"):
        cell.arm("panda")
    with pytest.raises(ConfigError, match="unknown robot id 7"):
        cell.arm_by_id(7)
    assert [a.name for a in cell.subset(["ur10"]).arms] == ["ur10"]


def test_bad_profile_names_the_field(tmp_path):
    with open(data_path("config", "arms", "ur10.yaml")) as f:
        data = yaml.safe_load(f)
    data["model"] = data_path(data["model"])
    data["home"][2] = 4.0
    path = tmp_path / "ur10.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="home: elbow_joint = 4 is outside its limits"):
        load_arm_profile(str(path))
    path.write_text("joints: [unclosed")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_arm_profile(str(path))


def test_cli_help_and_cell_command(tmp_path):
    run = lambda *a: subprocess.run([sys.executable, "-m", "ambots", *a], capture_output=True, text=True)
    r = run("--help")
    assert r.returncode == 0 and "cell" in r.stdout
    out = tmp_path / "cell.urdf"
    r = run("cell", "--urdf", str(out))
    assert r.returncode == 0, r.stderr
    assert "R1 ur10" in r.stdout and "inbox /ambots/ur_topic" in r.stdout and "reaches 50/50" in r.stdout
    ET.parse(str(out))
    r = run("cell", "--cell", str(tmp_path / "missing.yaml"))
    assert r.returncode == 2 and "missing.yaml: cell file not found" in r.stderr
    assert "Traceback" not in r.stderr
