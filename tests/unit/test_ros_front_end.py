"""The front end's ROS transport (ambots.ros.front_end.RosLink) while it
closes: a numbered message that the hub forwarded arrives in a subscriber
callback after the link unregistered its publisher (quitting the menu
while an arm reports).  Its acknowledgement is dropped; it must not raise
in rospy's callback thread ("bad callback ... publish() to a closed topic",
seen once in CI from `rosrun ambots front_end` quitting at once).  No ROS
master is needed: rospy makes the topics before a node registers them."""
import rospy
from std_msgs.msg import String

from ambots.protocol import ArmState, Status, encode
from ambots.ros.front_end import RosLink


def test_a_report_arriving_while_the_link_closes_is_not_answered_and_raises_nothing():
    link = RosLink()
    sent = []
    publish = link._pub.publish
    link._pub.publish = lambda msg: (sent.append(msg.data), publish(msg))
    link.close()
    report = encode(Status(0, ArmState.PRINTING, 1, 5, 10.0, sender=1, seq=7))
    link._on_message(String(report))          # the callback thread's call
    assert sent == []


def test_a_closed_topic_while_the_link_is_open_is_still_an_error():
    link = RosLink()
    link._pub.unregister()                    # closed under an open link: not the node going down
    try:
        assert not rospy.is_shutdown()
        raised = None
        try:
            link._on_message(String(encode(Status(0, ArmState.PRINTING, 1, 5, 10.0, sender=1, seq=8))))
        except rospy.ROSException as exc:
            raised = exc
        assert raised is not None and "unregistered" in str(raised)
    finally:
        link.close()
