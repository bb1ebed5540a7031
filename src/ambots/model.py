"""Robot descriptions: one arm's URDF from its xacro model and profile, and
the whole cell's URDF (world + bed + N arms with per-arm prefixes) generated
from a cell config -- the N-arm counterpart of a hand-written dual-arm xacro.
"""
import xml.etree.ElementTree as ET

from ambots.config import ArmInstance, ArmProfile, Cell
from ambots.errors import ConfigError, KinematicsError

__all__ = ["arm_urdf", "cell_urdf", "arm_kinematics"]


def arm_urdf(profile: ArmProfile, prefix=""):
    """URDF string of one arm: its xacro ``model`` processed with ``prefix``
    (e.g. ``ur10/``) and the profile (joint limits, tool offset).  xacro
    reads both files; their text is kept per (model, profile, prefix) while
    neither file changes (a job builds the same arm's kinematics about 20
    times: 70 ms each)."""
    key = _urdf_key(profile, prefix)
    text = _URDF.get(key)
    if text is None:
        import xacro
        try:
            doc = xacro.process_file(profile.model, mappings={"prefix": prefix, "profile": profile.path})
        except Exception as exc:  # xacro raises plain Exceptions of several kinds
            raise KinematicsError("%s: xacro failed: %s" % (profile.model, exc)) from None
        _check_bodies_drawn(profile, doc, prefix)
        text = _URDF[key] = doc.toxml()
    return text


_URDF = {}


def _urdf_key(profile, prefix=""):
    return profile.model, profile.path, prefix, _stamp(profile.model), _stamp(profile.path)


def prefetch_urdfs(profiles):
    """Run xacro for the ``profiles`` whose URDF (:func:`arm_urdf`, no
    prefix) is not kept yet in a worker process (:mod:`ambots.parallel`;
    0.15 s an arm, while the job reads its model); returns a function that
    waits for them and keeps them (raising xacro's error, if any), and
    ``cancel``, which drops them."""
    from ambots.parallel import Forked, workers
    todo = list({_urdf_key(p): p for p in profiles if _urdf_key(p) not in _URDF}.values())
    if not todo or workers() < 2:
        return (lambda: None), (lambda: None)
    job = Forked(lambda: {_urdf_key(p): arm_urdf(p) for p in todo})
    return (lambda: _URDF.update(job.result())), job.cancel


def _stamp(path):
    """A file's (mtime ns, size), None when it cannot be read (xacro then says why)."""
    import os
    try:
        st = os.stat(path)
    except (OSError, TypeError):
        return None
    return st.st_mtime_ns, st.st_size


def _check_bodies_drawn(profile, doc, prefix):
    """Every link named in the profile's ``bodies:`` must be a link of the
    model that draws them (its xacro calls ``ambots_link_bodies`` in it): a
    misspelt link name would otherwise leave the bodies out unnoticed."""
    links = {e.getAttribute("name")[len(prefix):]: e for e in doc.getElementsByTagName("link")}
    for link, bodies in profile.bodies.items():
        if link not in links:
            raise ConfigError(profile.path, "bodies.%s" % link, "the model %s has no link %r (its links: %s)"
                              % (profile.model, link, ", ".join(sorted(links))))
        drawn = len(links[link].getElementsByTagName("collision"))
        if drawn < len(bodies):
            raise ConfigError(profile.path, "bodies.%s" % link, "the model %s draws %d collision bodies on this "
                              "link, fewer than the profile's %d (does its xacro call ambots_link_bodies there?)"
                              % (profile.model, drawn, len(bodies)))


def _fmt(v):
    return " ".join(repr(float(x)) for x in v)


def cell_urdf(cell: Cell):
    """URDF string of the whole cell: a ``world`` link, the print bed (a box
    whose top face centre is the bed pose) and every arm of the cell, each
    with its own prefix and a fixed joint world -> ``<arm>/base_link``."""
    robot = ET.Element("robot", name=cell.name)
    ET.SubElement(robot, "link", name=cell.world_frame)
    bed = ET.SubElement(robot, "link", name="bed")
    sx, sy, sz = cell.bed.size
    for tag in ("visual", "collision"):
        el = ET.SubElement(bed, tag)
        ET.SubElement(el, "origin", xyz=_fmt((0, 0, -sz / 2)), rpy="0 0 0")
        ET.SubElement(ET.SubElement(el, "geometry"), "box", size=_fmt((sx, sy, sz)))
        if tag == "visual":
            ET.SubElement(ET.SubElement(el, "material", name="bed"), "color", rgba="0.85 0.85 0.8 1")
    j = ET.SubElement(robot, "joint", name="bed_joint", type="fixed")
    ET.SubElement(j, "parent", link=cell.world_frame)
    ET.SubElement(j, "child", link="bed")
    ET.SubElement(j, "origin", xyz=_fmt(cell.bed.xyz), rpy=_fmt(cell.bed.rpy))
    for arm in cell.arms:
        part = ET.fromstring(arm_urdf(arm.profile, arm.prefix))
        for el in part:
            if el.tag in ("link", "joint"):
                robot.append(el)
        j = ET.SubElement(robot, "joint", name=arm.prefix + "base_joint", type="fixed")
        ET.SubElement(j, "parent", link=cell.world_frame)
        ET.SubElement(j, "child", link=arm.frame(arm.profile.base_link))
        ET.SubElement(j, "origin", xyz=_fmt(arm.base_xyz), rpy=_fmt(arm.base_rpy))
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode")


def arm_kinematics(arm):
    """:class:`~ambots.kinematics.ArmKinematics` base_link -> nozzle of an arm
    (an :class:`ArmInstance` of a cell, or a bare :class:`ArmProfile`); an arm
    with joints to spare returns along its self-motion to its home posture
    while it follows a path (``rest``)."""
    from ambots.kinematics import ArmKinematics
    profile = arm.profile if isinstance(arm, ArmInstance) else arm
    return ArmKinematics.from_urdf(arm_urdf(profile), base=profile.base_link, tip=profile.tool_link,
                                   trail=profile.tool_trail, rest=profile.home)
