"""ROS side of a cell: robot descriptions, one robot_state_publisher per arm
namespace, static transforms world -> each arm base and the bed, the bed
marker, optional home joint states (until firmware nodes take over) and,
on request, RViz with the cell's config."""
import os

import rospy
import tf2_ros
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker

from ambots import data_path
from ambots.model import arm_urdf
from ambots.rviz import CELL_MARKERS_TOPIC, rviz_config
from ambots.ros.convert import transform_msg


class CellPublisher:
    def __init__(self, cell, publish_home=True, rviz=False):
        self.cell, self.publish_home, self.rviz = cell, publish_home, rviz
        self._launch = None

    def start(self):
        import roslaunch
        from roslaunch.core import Node
        for arm in self.cell.arms:
            rospy.set_param("/%s/robot_description" % arm.name, arm_urdf(arm.profile, arm.prefix))
        self._launch = roslaunch.scriptapi.ROSLaunch()
        self._launch.start()
        rospy.on_shutdown(self._launch.stop)
        for arm in self.cell.arms:
            self._launch.launch(Node("robot_state_publisher", "robot_state_publisher",
                                     name="robot_state_publisher", namespace="/" + arm.name))
        self._static = tf2_ros.StaticTransformBroadcaster()
        world = self.cell.world_frame
        tfs = [transform_msg(world, "bed", self.cell.bed.pose)]
        tfs += [transform_msg(world, arm.frame(arm.profile.base_link), arm.base_pose) for arm in self.cell.arms]
        self._static.sendTransform(tfs)
        self._bed_pub = rospy.Publisher(CELL_MARKERS_TOPIC, Marker, queue_size=1, latch=True)
        self._bed_pub.publish(self._bed_marker())
        if self.rviz:
            self._launch.launch(Node("rviz", "rviz", name="rviz", args="-d " + self.rviz_config_path()))
        self._home_pubs = {a.name: rospy.Publisher("/%s/joint_states" % a.name, JointState, queue_size=1)
                           for a in self.cell.arms} if self.publish_home else {}

    def rviz_config_path(self):
        shipped = data_path("config", "rviz", self.cell.name + ".rviz")
        if os.path.exists(shipped):
            return shipped
        path = os.path.join(os.environ.get("ROS_HOME", os.path.expanduser("~/.ros")), "ambots",
                            self.cell.name + ".rviz")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(rviz_config(self.cell))
        return path

    def _bed_marker(self):
        m = Marker()
        m.header.frame_id = "bed"
        m.ns, m.id, m.type, m.action = "bed", 0, Marker.CUBE, Marker.ADD
        sx, sy, sz = self.cell.bed.size
        m.pose.position.z = -sz / 2
        m.pose.orientation.w = 1.0
        m.scale.x, m.scale.y, m.scale.z = sx, sy, sz
        m.color.r, m.color.g, m.color.b, m.color.a = 0.85, 0.85, 0.8, 1.0
        return m

    def spin(self, rate_hz=20.0):
        rate = rospy.Rate(rate_hz)
        msgs = {}
        for arm in self.cell.arms:
            msg = JointState()
            msg.name = [arm.prefix + j for j in arm.profile.joint_names]
            msg.position = list(arm.profile.home)
            msgs[arm.name] = msg
        while not rospy.is_shutdown():
            now = rospy.Time.now()
            for name, pub in self._home_pubs.items():
                msgs[name].header.stamp = now
                pub.publish(msgs[name])
            try:
                rate.sleep()
            except rospy.ROSInterruptException:
                break
