"""Names shared by every node: topics, node names and protocol node ids.

One place, so that the hub, the firmware nodes and the front end agree.
Per-arm names are derived from the arm's instance name in the cell; an
arm's inbox topic is the cell's (``ArmInstance.inbox``).
"""
from ambots import protocol

#: every A-series message to anyone goes here (std_msgs/String); the hub routes it
HUB_TOPIC = "/ambots/communication_hub_topic"
#: the hub's refusals and the arms' error reports, human-readable (std_msgs/String)
ERROR_TOPIC = "/ambots/errors"
#: per-arm progress aggregated by the hub, one JSON object (std_msgs/String)
PROGRESS_TOPIC = "/ambots/progress"
#: the front end's inbox (acks and status for it), std_msgs/String
FRONT_END_TOPIC = "/ambots/front_end_topic"

#: protocol node id of the hub (``S1001``)
HUB_ID = protocol.HUB
#: protocol node id of the front end; robot ids are 0..999 (from the cell)
FRONT_END_ID = protocol.FRONT_END
#: ROS node name of the front end (the hub checks callers against it)
FRONT_END_NODE = "/front_end"
#: ROS node name of the hub
HUB_NODE = "/communication_hub"


def default_arm_topic(arm_name):
    """The inbox of an arm whose cell entry names none: ``/<arm>/firmware_topic``."""
    return "/%s/firmware_topic" % arm_name


def arm_topic(arm):
    """The inbox of ``arm``'s firmware (std_msgs/String): its cell entry's
    ``topic`` (``ambots.config.ArmInstance.inbox``); the default cell keeps
    the original's ``/ambots/kinova_topic`` and ``/ambots/ur_topic``."""
    return arm.inbox


def arm_node(arm_name):
    """ROS node name of arm ``arm_name``'s firmware."""
    return "/%s/firmware" % arm_name


def joint_states_topic(arm_name):
    return "/%s/joint_states" % arm_name

#: the one clock's bookkeeping (std_msgs/String, JSON): each firmware after a
#: step ({"arm": name, ...}: ambots.clock.ArmReady) and the hub after each
#: message ({"hub": ...}: ambots.clock.HubState); the clock node reads it
CLOCK_READY_TOPIC = "/ambots/clock/ready"
