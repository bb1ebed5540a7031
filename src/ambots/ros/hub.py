"""ROS side of the communication hub: one subscriber on ``topics.HUB_TOPIC``
feeding :class:`ambots.hub.Hub` with each message's caller id, publishers
for every post it returns, a timer for retransmissions and a timer that
republishes the progress (latched) even without news.

Fault injection (tests, ``make faults``): with a :class:`ambots.faults.FaultSpec`
that is active, everything the hub receives passes through one
:class:`~ambots.faults.FaultyChannel` and everything it publishes on the
arms' and the front end's inboxes through another (progress and error
topics are not faulted); a fast timer releases what is due.  The counts
are in the progress JSON under ``"faults"``.

Crash safety (``state_file``): before the hub publishes anything that
answers a message -- acks, forwards -- it writes :meth:`ambots.hub.Hub.snapshot`
(duplicate windows, unacknowledged forwards) atomically to ``state_file``
with the ROS run id.  A hub restarted in the same run (roslaunch respawn
after ``kill -9``) restores it: what the old hub acknowledged is forwarded,
once, under the numbers the old hub gave it."""
import json
import threading
import time

import rospy
from std_msgs.msg import String

from ambots import topics
from ambots.checkpoint import read_json, write_json
from ambots.clock import HubState
from ambots.faults import FaultSpec, FaultyChannel
from ambots.ros import ASeriesLog, WallTimer

#: the hub keeps time by the wall: retries, fault delays and progress go on
#: while a simulated clock (/clock) waits for the messages to arrive
_now = time.monotonic


class HubNode:
    """Connects ``hub`` to ROS.  ``retry_period`` (s) is how often due
    retransmissions are looked for; ``progress_period`` (s) how often the
    progress is republished.  rospy calls back from several threads, so
    every call into the hub holds one lock."""

    def __init__(self, hub, retry_period=0.05, progress_period=1.0, faults=FaultSpec(), state_file=None,
                 run_id="", debug=False):
        self.hub = hub
        self.log = ASeriesLog("hub", debug)
        self.state_file, self.run_id = state_file, run_id
        self.resumed = False
        self.retry_period, self.progress_period = retry_period, progress_period
        self._lock = threading.Lock()
        self._pubs = {}
        self.faults = faults if faults.active else None
        if self.faults:
            self._in = FaultyChannel(faults, stream=1)
            self._out = FaultyChannel(faults, stream=2)
        self.retries = 0

    def start(self):
        """Restore the state of a crashed predecessor (same ROS run), then
        advertise, subscribe and start the timers."""
        if self.state_file:
            doc = read_json(self.state_file)
            if doc is not None and doc.get("run_id") == self.run_id:
                self.hub.restore(doc["hub"], _now())
                self.resumed = True
                rospy.logwarn("communication hub: resumed from its checkpoint (%d forwards to deliver)",
                              len(self.hub.sender.pending))
        self._inboxes = set(self.hub.registry.inboxes)
        for topic in self.hub.registry.inboxes + [topics.ERROR_TOPIC]:
            self._pubs[topic] = rospy.Publisher(topic, String, queue_size=1000)
        self._pubs[topics.PROGRESS_TOPIC] = rospy.Publisher(topics.PROGRESS_TOPIC, String,
                                                            queue_size=1, latch=True)
        rospy.Subscriber(topics.HUB_TOPIC, String, self._on_message, queue_size=1000)
        # latched: the clock learns the hub's state as soon as it connects
        self._clock_ready = rospy.Publisher(topics.CLOCK_READY_TOPIC, String, queue_size=1000, latch=True)
        self._state = None
        with self._lock:
            self._tell_clock()
        WallTimer(self.retry_period, self._on_retry_timer)
        WallTimer(self.progress_period, self._on_progress_timer)
        if self.faults:
            rospy.logwarn("communication hub: injecting faults %s", self.faults)
            WallTimer(0.002, self._on_fault_timer)

    def _on_message(self, msg):
        caller = msg._connection_header["callerid"]
        self.log.received(caller, msg.data)
        with self._lock:
            if self.faults:
                self._in.push((msg.data, caller), _now())
                return
            self._publish(self.hub.handle(msg.data, caller, _now()))

    def _on_fault_timer(self):
        with self._lock:
            now = _now()
            posts = []
            for text, caller in self._in.pop_due(now):
                posts += self.hub.handle(text, caller, now)
            self._publish(posts)                  # one save for the batch
            for post in self._out.pop_due(now):
                self.log.sent(post.topic, post.text)
                self._pubs[post.topic].publish(String(post.text))

    def _on_retry_timer(self):
        with self._lock:
            posts = self.hub.tick(_now())
            self.retries += sum(1 for p in posts if p.topic != topics.ERROR_TOPIC)
            self._publish(posts, save=False)     # retransmissions: nothing new to save

    def _on_progress_timer(self):
        with self._lock:
            self._pubs[topics.PROGRESS_TOPIC].publish(String(self.progress_json()))

    def progress_json(self):
        """The hub's progress JSON plus its delivery counts (lock held)."""
        doc = json.loads(self.hub.progress_json(_now()))
        doc["hub"] = {"retries": self.retries, "resumed": self.resumed}
        if self.faults:
            doc["faults"] = {"spec": str(self.faults), "in": self._in.counts.as_dict(),
                             "out": self._out.counts.as_dict()}
        return json.dumps(doc)

    def _save(self):
        write_json(self.state_file, {"run_id": self.run_id, "hub": self.hub.snapshot()})

    def _tell_clock(self):
        """What the clock (:mod:`ambots.clock`) needs to know that every message
        is delivered: per sender the highest number admitted, per arm the last
        forward, how many forwards to arms are unacknowledged (what the front
        end is told does not move an arm; lock held; sent when it changed,
        before the posts that follow from it)."""
        hub = self.hub
        arms = hub.registry.arms
        state = HubState({i: hub.receiver.top(i) for i in hub.registry.nodes if hub.receiver.top(i) is not None},
                         {i: hub.sender.last_to(i) for i in arms if hub.sender.last_to(i) is not None},
                         sum(1 for o in hub.sender.pending if o.destination in arms))
        if state != self._state:
            self._state = state
            self._clock_ready.publish(String(json.dumps({"hub": state.as_dict()})))

    def _publish(self, posts, save=True):
        """Publish ``posts`` (lock held); with a state file, the state that
        produced them is saved first."""
        self._tell_clock()
        if save and self.state_file and any(p.topic in self._inboxes for p in posts):
            self._save()
        now = _now()
        for post in posts:
            if post.topic == topics.ERROR_TOPIC:
                rospy.logwarn(post.text)
            if post.topic == topics.PROGRESS_TOPIC:
                self._pubs[post.topic].publish(String(self.progress_json()))
            elif self.faults and post.topic != topics.ERROR_TOPIC:
                self._out.push(post, now)
            else:
                if post.topic != topics.ERROR_TOPIC:
                    self.log.sent(post.topic, post.text)
                self._pubs[post.topic].publish(String(post.text))
