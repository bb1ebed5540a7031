"""Arm profiles (``config/arms/<arm>.yaml``) and cells (``config/cells/<cell>.yaml``).

One source of truth per concern: an arm profile says what the arm *is* (model
file, joints and limits, tool offset, colour, driver names); a cell says which
arms stand where (base poses in the ``world`` frame) around which print bed.
Every value is checked when it is loaded, and a bad one raises
:class:`~ambots.errors.ConfigError` naming the file and the field.

Units: metres and radians (REP 103).
"""
import math
import os
from dataclasses import dataclass, field
from typing import Tuple

import numpy as np
import yaml

from ambots import data_path, protocol, topics
from ambots.errors import ConfigError

__all__ = ["ArmProfile", "ArmInstance", "Bed", "Cell", "Capsule", "load_arm_profile", "load_cell",
           "pose_matrix", "resolve_path", "DRIVER_NUMBERS", "DRIVER_NAMES", "BODY_KINDS", "HEAD_TIP_GAP",
           "TOOL_TURNS"]

#: optional numbers (> 0) of a profile's ``driver:`` section: s between trajectory points the
#: controller requires, rad/s it accepts on every joint (see :mod:`ambots.trajectory`)
DRIVER_NUMBERS = ("sample_period", "max_joint_speed")
#: optional names of a profile's ``driver:`` section (topics relative to the arm's namespace)
DRIVER_NAMES = ("joint_states_topic", "extruder_topic", "extruder_joint")
#: the kinds of collision body a profile's ``bodies:`` and ``tool.head:`` entries describe
#: (see :func:`_read_body`)
BODY_KINDS = ("tube", "housing", "ball")
#: every print head body stays at least this far behind the nozzle tip (m), so that a
#: nozzle printing on the part does not touch it (the profiles keep 5 mm)
HEAD_TIP_GAP = 0.002
#: a profile's ``tool.turn``, the turn about the nozzle axis: ``free`` (the IK keeps it near where
#: it was) or ``toward_base`` (a nozzle off the flange's axis keeps the flange towards the arm's
#: base, so the wrist and forearm trail behind the nozzle, away from the arms across the bed)
TOOL_TURNS = ("free", "toward_base")


def resolve_path(path, relative_to=None):
    """A config path as written by a user: absolute, relative to the current
    folder, relative to ``relative_to`` (the file that names it), or relative
    to the package root (``config/arms/ur10.yaml``)."""
    if os.path.isabs(path):
        return path
    candidates = [path]
    if relative_to:
        candidates.append(os.path.join(os.path.dirname(relative_to), path))
    candidates.append(data_path(path))
    for c in candidates:
        if os.path.exists(c):
            return os.path.abspath(c)
    return os.path.abspath(candidates[-1])


def pose_matrix(xyz, rpy):
    """4x4 homogeneous transform from translation ``xyz`` (m) and fixed-axis
    roll-pitch-yaw ``rpy`` (rad), URDF convention: R = Rz(y) Ry(p) Rx(r)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    T = np.eye(4)
    T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]
    T[:3, 3] = xyz
    return T


class _Reader:
    """Checked access to a YAML mapping; errors name ``path`` and the field."""

    def __init__(self, path, data, prefix=""):
        self.path, self.data, self.prefix = path, data, prefix
        if not isinstance(data, dict):
            raise ConfigError(path, prefix or None, "expected a mapping, got %s" % type(data).__name__)

    def _name(self, key):
        if isinstance(key, int):                    # an item of a list read as {index: item}
            return "%s[%d]" % (self.prefix, key)
        return "%s.%s" % (self.prefix, key) if self.prefix else key

    def get(self, key, default=KeyError):
        if key not in self.data:
            if default is KeyError:
                raise ConfigError(self.path, self._name(key), "missing field")
            return default
        return self.data[key]

    def str(self, key, default=KeyError):
        v = self.get(key, default)
        if not isinstance(v, str) or not v:
            raise ConfigError(self.path, self._name(key), "expected a non-empty string, got %r" % (v,))
        return v

    def num(self, key, default=KeyError, positive=False):
        v = self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(self.path, self._name(key), "expected a finite number, got %r" % (v,))
        if positive and v <= 0:
            raise ConfigError(self.path, self._name(key), "must be > 0, got %r" % (v,))
        return float(v)

    def vec(self, key, n, default=KeyError):
        v = self.get(key, default)
        if (not isinstance(v, (list, tuple)) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                           for x in v)):
            raise ConfigError(self.path, self._name(key), "expected a list of %d finite numbers, got %r" % (n, v))
        return tuple(float(x) for x in v)

    def sub(self, key, default=KeyError):
        v = self.get(key, default)
        return _Reader(self.path, v, self._name(key))

    def items(self, key):
        v = self.get(key)
        if not isinstance(v, list) or not v:
            raise ConfigError(self.path, self._name(key), "expected a non-empty list")
        return [_Reader(self.path, item, "%s[%d]" % (self._name(key), i)) for i, item in enumerate(v)]

    def only(self, allowed):
        """Refuse keys other than ``allowed`` (a typo would silently drop a body)."""
        unknown = sorted(str(k) for k in self.data if k not in allowed)
        if unknown:
            raise ConfigError(self.path, self._name(unknown[0]), "unknown field (expected one of: %s)"
                              % ", ".join(allowed))


class _Loader(yaml.SafeLoader):
    """The safe loader, refusing a key given twice in a mapping (plain YAML
    keeps the last one silently)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                duplicate = key in seen
            except TypeError:        # unhashable: construct_mapping says so
                break
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    "while reading a mapping", node.start_mark, "duplicate key %r" % (key,),
                    key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


def _load_yaml(path, what):
    if not os.path.isfile(path):
        raise ConfigError(path, None, "%s file not found" % what)
    try:
        with open(path, encoding="utf-8") as f:
            data = yaml.load(f, Loader=_Loader)
    except yaml.YAMLError as exc:
        raise ConfigError(path, None, "not valid YAML: %s" % exc) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(path, None, "not UTF-8 text (byte %d): not a YAML file" % exc.start) from None
    except OSError as exc:
        raise ConfigError(path, None, "cannot read: %s" % (exc.strerror or exc)) from None
    return _Reader(path, data)


@dataclass(frozen=True)
class JointLimit:
    name: str
    lower: float           #: rad (-inf for a continuous joint)
    upper: float           #: rad (+inf for a continuous joint)
    velocity: float        #: rad/s
    acceleration: float    #: rad/s^2
    continuous: bool = False


@dataclass(frozen=True)
class Capsule:
    """One collision body of a profile: the points within ``radius`` of the
    segment ``a`` - ``b`` (a ball when they coincide), in its link's frame (m).
    The model draws it as the cylinder of length ``|b - a| + 2 radius`` around
    the segment, which :class:`ambots.collision.ArmBody` turns back into it."""
    name: str
    a: Tuple[float, float, float]
    b: Tuple[float, float, float]
    radius: float


def _read_body(r):
    """A :class:`Capsule` from one ``bodies:`` or ``tool.head:`` entry, one of

    * ``{tube: [[x, y, z], [x, y, z]], radius: r}``: within r of the segment
      (a link tube between two joint centres);
    * ``{housing: [x, y, z], axis: [x, y, z], reach: h, radius: r}``: a joint
      housing, coaxial with ``axis`` through the centre: the segment from
      ``h`` before to ``h`` after the centre along the axis, plus r (so it
      covers a cylinder of radius r reaching h beyond the centre both ways);
    * ``{ball: [x, y, z], radius: r}``;

    each with an optional ``name``.  Metres, in the link's own frame."""
    kinds = [k for k in BODY_KINDS if k in r.data]
    if len(kinds) != 1:
        raise ConfigError(r.path, r.prefix, "expected exactly one of %s, got %s"
                          % (", ".join(BODY_KINDS), ", ".join(kinds) or "none"))
    kind = kinds[0]
    r.only({"tube": ("tube", "radius", "name"), "housing": ("housing", "axis", "reach", "radius", "name"),
            "ball": ("ball", "radius", "name")}[kind])
    name = r.str("name", kind)
    radius = r.num("radius", positive=True)
    a, b = {"ball": lambda: (r.vec("ball", 3),) * 2, "tube": lambda: _tube(r), "housing": lambda: _housing(r)}[kind]()
    return Capsule(name, a, b, radius)


def _tube(r):
    """The two ends of a ``tube:`` entry."""
    ends = r.get("tube")
    if not isinstance(ends, list) or len(ends) != 2:
        raise ConfigError(r.path, r.prefix + ".tube", "expected two points [[x, y, z], [x, y, z]], got %r" % (ends,))
    points = _Reader(r.path, dict(enumerate(ends)), r.prefix + ".tube")
    return points.vec(0, 3), points.vec(1, 3)


def _housing(r):
    """The segment of a ``housing:`` entry: ``reach`` before and after its
    centre along its axis."""
    centre, axis = np.array(r.vec("housing", 3)), np.array(r.vec("axis", 3))
    reach = r.num("reach")
    if reach < 0:
        raise ConfigError(r.path, r.prefix + ".reach", "must be >= 0, got %r" % (reach,))
    norm = float(np.linalg.norm(axis))
    if not norm > 1e-9:
        raise ConfigError(r.path, r.prefix + ".axis", "must not be zero, got %r" % (list(axis),))
    return tuple(tuple(float(x) for x in centre + s * reach * axis / norm) for s in (-1.0, 1.0))


def _read_bodies(r):
    """{link: (Capsule, ...)} from the optional ``bodies:`` mapping of link
    names (without prefix) to lists of bodies."""
    if "bodies" not in r.data or r.data["bodies"] is None:
        return {}
    bodies = r.sub("bodies")
    out = {}
    for link in bodies.data:
        if not isinstance(link, str) or not link:
            raise ConfigError(r.path, "bodies", "link names must be non-empty strings, got %r" % (link,))
        out[link] = tuple(_read_body(b) for b in bodies.items(link))
    return out


def _tool_trail(xyz, rpy):
    """The flange's origin seen from the nozzle, in the nozzle frame, without
    its part along the nozzle axis, made unit (None when the nozzle is on the
    flange's axis, within 1 mm)."""
    T = pose_matrix(xyz, rpy)
    flange = -T[:3, :3].T @ T[:3, 3]
    flange[2] = 0.0
    norm = float(np.linalg.norm(flange))
    return None if norm < 1e-3 else flange / norm


def _read_turn(tool):
    """``tool.turn`` (default ``free``); ``toward_base`` needs a nozzle off the
    flange's axis, or the turn would move nothing but the head."""
    turn = tool.str("turn", "free")
    if turn not in TOOL_TURNS:
        raise ConfigError(tool.path, tool.prefix + ".turn", "expected one of %s, got %r" % (", ".join(TOOL_TURNS), turn))
    if turn != "free" and _tool_trail(tool.vec("xyz", 3), tool.vec("rpy", 3, (0.0, 0.0, 0.0))) is None:
        raise ConfigError(tool.path, tool.prefix + ".turn",
                          "%s needs the nozzle off the flange's axis (tool.xyz, tool.rpy put it within 1 mm of "
                          "it): turning about the nozzle axis would then move only the print head" % turn)
    return turn


def _read_head(tool):
    """The print head's bodies (``tool.head:``, nozzle frame: the tip at the
    origin, z out of the tip), each kept :data:`HEAD_TIP_GAP` behind the tip."""
    head = tuple(_read_body(b) for b in tool.items("head"))
    for i, c in enumerate(head):
        front = max(c.a[2], c.b[2]) + c.radius
        if front > -HEAD_TIP_GAP:
            raise ConfigError(tool.path, "%s.head[%d]" % (tool.prefix, i),
                              "%r reaches %.1f mm from the tip (z + radius = %.4f m); the head must stay at "
                              "least %.0f mm behind it (z < 0 is behind the tip), or printing on the part "
                              "would be contact" % (c.name, -front * 1000.0, front, HEAD_TIP_GAP * 1000.0))
    return head


@dataclass(frozen=True)
class ArmProfile:
    """What an arm is (one ``config/arms/<arm>.yaml``)."""
    path: str
    name: str
    brand: str
    model: str                    #: absolute path of the xacro/URDF model
    base_link: str
    flange_link: str
    tool_xyz: Tuple[float, float, float]
    tool_rpy: Tuple[float, float, float]
    reach: float                  #: m
    joints: Tuple[JointLimit, ...]
    home: Tuple[float, ...]       #: rad
    velocity_scaling: float
    colour: Tuple[float, float, float, float]
    driver_joint_names: Tuple[str, ...]
    driver_command_topic: str
    driver_options: dict = field(default_factory=dict)
    #: {link: (Capsule, ...)}: collision bodies besides the model's own (joint housings, link tubes)
    bodies: dict = field(default_factory=dict)
    #: the print head's bodies on the ``nozzle`` link (nozzle frame)
    head: Tuple[Capsule, ...] = ()
    #: the turn about the nozzle axis (``tool.turn``): one of :data:`TOOL_TURNS`
    tool_turn: str = "free"

    @property
    def joint_names(self):
        return tuple(j.name for j in self.joints)

    @property
    def tool_trail(self):
        """For ``tool.turn: toward_base``: the unit direction (3,), in the
        nozzle frame, from the nozzle towards the flange's axis, perpendicular
        to the nozzle (its z); the IK keeps it pointing at the arm's base
        (:class:`ambots.kinematics.ArmKinematics`).  None when the turn is free."""
        if self.tool_turn == "free":
            return None
        return _tool_trail(self.tool_xyz, self.tool_rpy)

    @property
    def tool_link(self):
        return "nozzle"


def load_arm_profile(path):
    """Read and check an arm profile.  ``path`` may be relative to the package
    root (``config/arms/ur10.yaml``)."""
    path = resolve_path(path)
    r = _load_yaml(path, "arm profile")
    joints = []
    for j in r.items("joints"):
        cont = j.get("continuous", False)
        if not isinstance(cont, bool):       # bool("no") would be True: an unlimited joint
            raise ConfigError(path, j.prefix + ".continuous", "expected true or false, got %r" % (cont,))
        if any(jl.name == j.data.get("name") for jl in joints):
            raise ConfigError(path, j.prefix + ".name", "duplicate joint name %r" % j.data["name"])
        lower, upper = j.num("lower"), j.num("upper")
        if lower >= upper:
            raise ConfigError(path, j.prefix, "lower limit %g >= upper limit %g" % (lower, upper))
        joints.append(JointLimit(j.str("name"), -math.inf if cont else lower, math.inf if cont else upper,
                                 j.num("velocity", positive=True), j.num("acceleration", positive=True), cont))
    n = len(joints)
    home = r.vec("home", n)
    for jl, q in zip(joints, home):
        if not jl.lower <= q <= jl.upper:
            raise ConfigError(path, "home", "%s = %g is outside its limits [%g, %g]" % (jl.name, q, jl.lower, jl.upper))
    tool = r.sub("tool")
    tool.only(("xyz", "rpy", "head", "turn"))
    driver = r.sub("driver")
    names = driver.get("joint_names")
    if not isinstance(names, list) or len(names) != n or not all(isinstance(s, str) for s in names):
        raise ConfigError(path, "driver.joint_names", "expected %d joint names" % n)
    options = dict(driver.data)
    for key in ("joint_names", "command_topic"):
        options.pop(key, None)
    for key in DRIVER_NUMBERS:                 # the controller's constraints, as data (ambots.trajectory)
        if key in options:
            options[key] = driver.num(key, positive=True)
    for key in DRIVER_NAMES:
        if key in options:
            options[key] = driver.str(key)
    model = resolve_path(r.str("model"), path)
    if not os.path.isfile(model):
        raise ConfigError(path, "model", "model file %s not found" % model)
    scaling = r.num("velocity_scaling", 1.0, positive=True)
    if scaling > 1.0:
        raise ConfigError(path, "velocity_scaling", "must be in (0, 1], got %g" % scaling)
    return ArmProfile(
        path=path, name=r.str("name"), brand=r.str("brand", ""), model=model,
        base_link=r.str("base_link", "base_link"), flange_link=r.str("flange_link", "flange"),
        tool_xyz=tool.vec("xyz", 3), tool_rpy=tool.vec("rpy", 3, (0.0, 0.0, 0.0)),
        reach=r.num("reach", positive=True), joints=tuple(joints), home=home,
        velocity_scaling=scaling, colour=r.vec("filament_colour", 4),
        driver_joint_names=tuple(names), driver_command_topic=driver.str("command_topic"),
        driver_options=options, bodies=_read_bodies(r), head=_read_head(tool), tool_turn=_read_turn(tool))


@dataclass(frozen=True)
class ArmInstance:
    """One arm standing in a cell."""
    name: str            #: instance name; also the tf prefix ``<name>/`` and the ROS namespace
    id: int              #: robot id used by the A-series protocol (``R<id>``), 0..999
    profile: ArmProfile
    base_xyz: Tuple[float, float, float]
    base_rpy: Tuple[float, float, float]
    #: the firmware's inbox (std_msgs/String), where the hub forwards this arm's
    #: commands; the cell's ``topic``, default ``/<name>/firmware_topic``
    inbox: str = ""

    def __post_init__(self):
        if not self.inbox:
            object.__setattr__(self, "inbox", topics.default_arm_topic(self.name))

    @property
    def prefix(self):
        return self.name + "/"

    @property
    def base_pose(self):
        """4x4 pose of the arm's base_link in the world frame."""
        return pose_matrix(self.base_xyz, self.base_rpy)

    def frame(self, link):
        """tf frame id of one of this arm's links, e.g. ``ur10/nozzle``."""
        return self.prefix + link


@dataclass(frozen=True)
class Bed:
    size: Tuple[float, float, float]   #: x, y, thickness (m)
    xyz: Tuple[float, float, float]    #: centre of the top surface in world (m)
    rpy: Tuple[float, float, float]
    max_height: float = 0.15           #: printable height above the top surface (m)

    @property
    def pose(self):
        return pose_matrix(self.xyz, self.rpy)


@dataclass(frozen=True)
class Cell:
    """Which arms stand where, around which bed (one ``config/cells/<cell>.yaml``)."""
    path: str
    name: str
    bed: Bed
    arms: Tuple[ArmInstance, ...]
    world_frame: str = "world"

    def arm(self, name):
        for a in self.arms:
            if a.name == name:
                return a
        raise ConfigError(self.path, "arms", "unknown arm %r (this cell has: %s)"
                          % (name, ", ".join(a.name for a in self.arms)))

    def arm_by_id(self, robot_id):
        for a in self.arms:
            if a.id == robot_id:
                return a
        raise ConfigError(self.path, "arms", "unknown robot id %r (this cell has: %s)"
                          % (robot_id, ", ".join(str(a.id) for a in self.arms)))

    def subset(self, names):
        """The same cell with only the named arms (in the given order)."""
        return Cell(self.path, self.name, self.bed, tuple(self.arm(n) for n in names), self.world_frame)


_NAME_OK = set("abcdefghijklmnopqrstuvwxyz0123456789_")
_TOPIC_OK = _NAME_OK | set("ABCDEFGHIJKLMNOPQRSTUVWXYZ/")
#: topics of the hub, the front end and the cell's bookkeeping: no arm's inbox
_RESERVED_TOPICS = {topics.HUB_TOPIC, topics.ERROR_TOPIC, topics.PROGRESS_TOPIC, topics.FRONT_END_TOPIC,
                    topics.CLOCK_READY_TOPIC}


def _inbox(a, name, taken):
    """The ``topic`` of cell entry ``a`` (arm ``name``): a global ROS topic
    name not used by another arm nor by the hub's own topics."""
    topic = a.str("topic", topics.default_arm_topic(name))
    parts = topic.split("/")
    if (not topic.startswith("/") or not set(topic) <= _TOPIC_OK
            or any(not p or p[0].isdigit() for p in parts[1:])):
        raise ConfigError(a.path, a._name("topic"),
                          "%r: a global ROS topic name, e.g. /ambots/%s_topic" % (topic, name))
    if topic in _RESERVED_TOPICS or topic in taken:
        raise ConfigError(a.path, a._name("topic"), "%r is already the topic of %s"
                          % (topic, taken.get(topic, "the hub or the front end")))
    taken[topic] = "arm %r" % name
    return topic


def load_cell(path, min_base_distance=0.25):
    """Read and check a cell.  Arm bases closer than ``min_base_distance`` (m)
    are refused as overlapping."""
    path = resolve_path(path)
    if isinstance(min_base_distance, bool) or not isinstance(min_base_distance, (int, float)) \
            or not 0 <= min_base_distance < math.inf:
        raise ConfigError(path, "min_base_distance", "must be a finite number >= 0 (m), got %r"
                          % (min_base_distance,))
    r = _load_yaml(path, "cell")
    bed = r.sub("bed")
    size = bed.vec("size", 3)
    if min(size) <= 0:
        raise ConfigError(path, "bed.size", "every dimension must be > 0, got %r" % (size,))
    bed_pose = bed.sub("pose")
    the_bed = Bed(size, bed_pose.vec("xyz", 3), bed_pose.vec("rpy", 3, (0.0, 0.0, 0.0)),
                  bed.num("max_height", 0.15, positive=True))
    arms, names, ids, inboxes = [], set(), set(), {}
    for a in r.items("arms"):
        name = a.str("name")
        if not set(name) <= _NAME_OK or name[0].isdigit():
            raise ConfigError(path, a.prefix + ".name", "%r: use lower-case letters, digits and _" % name)
        if name in names:
            raise ConfigError(path, a.prefix + ".name", "duplicate arm name %r" % name)
        rid = a.get("id")
        if isinstance(rid, bool) or not isinstance(rid, int) or not 0 <= rid <= protocol.MAX_ROBOT:
            raise ConfigError(path, a.prefix + ".id", "expected an integer 0..%d (an A-series robot "
                              "id; %d is the front end, %d the hub), got %r"
                              % (protocol.MAX_ROBOT, protocol.FRONT_END, protocol.HUB, rid))
        if rid in ids:
            raise ConfigError(path, a.prefix + ".id", "duplicate robot id %d" % rid)
        prof_path = resolve_path(a.str("profile"), path)
        try:
            profile = load_arm_profile(prof_path)
        except ConfigError as exc:
            raise ConfigError(path, a.prefix + ".profile", str(exc)) from None
        base = a.sub("base")
        arms.append(ArmInstance(name, rid, profile, base.vec("xyz", 3), base.vec("rpy", 3, (0.0, 0.0, 0.0)),
                                _inbox(a, name, inboxes)))
        names.add(name)
        ids.add(rid)
    for i, a in enumerate(arms):
        for b in arms[:i]:
            d = float(np.linalg.norm(np.subtract(a.base_xyz, b.base_xyz)))
            if d < min_base_distance:
                raise ConfigError(path, "arms", "bases of %r and %r overlap: %.3f m apart (minimum %.2f m)"
                                  % (b.name, a.name, d, min_base_distance))
    return Cell(path, r.str("name"), the_bed, tuple(arms), r.str("world_frame", "world"))


def default_cell_path():
    """The cell used when none is given: Kinova Gen3 and UR10 facing each other."""
    return data_path("config", "cells", "kinova_ur10.yaml")
