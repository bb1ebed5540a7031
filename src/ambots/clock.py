"""The one clock of a simulated cell: when it may move on, and to when.

Every node of a simulated cell reads ROS time; the clock node
(``nodes/clock``) publishes it on ``/clock`` and decides its steps here.
The clock moves from T to T' only when

* every arm has finished its step up to T (its firmware's runner has
  advanced to T and everything it sent is acknowledged), and
* every message sent up to T has been delivered and executed: the hub has
  admitted every arm's last message, nothing it forwarded is unacknowledged,
  and every arm has executed the hub's last forward to it.

So every arm, the hub, TF, RViz and the capture see the same instant, and a
report sent at T reaches the arm waiting for it before anything moves past T.

T' is the earliest of: T + ``max_step``; the next *event* of any arm (the end
of the block it is executing, where it reports or reaches a barrier: a
report therefore happens exactly at a step, and the arm it releases starts
then, as in the offline run); and, at ``speed`` N, N times the wall time
since the last step.  While no arm is printing the clock follows the wall
(``idle_speed``).  Times in seconds.
"""
import math
from dataclasses import dataclass, field
from typing import Dict, Optional

from ambots.reliable import seq_diff

__all__ = ["ArmReady", "HubState", "Lockstep", "TOLERANCE_S"]

#: times closer than this are the same instant (ROS time is integer ns)
TOLERANCE_S = 1e-6


@dataclass(frozen=True)
class ArmReady:
    """What a firmware says after a step: its runner is at ``t``; its next
    event (block end) at ``next_event`` (None: none of its own, it waits,
    pauses or is idle); ``active``: it is printing; ``unacked``: its messages
    not yet acknowledged; ``last_q``: the number of its last message sent;
    ``hub_q``: the highest number of the hub's messages it has executed."""
    t: float
    next_event: Optional[float] = None
    active: bool = False
    unacked: int = 0
    last_q: Optional[int] = None
    hub_q: Optional[int] = None

    @classmethod
    def from_dict(cls, d):
        return cls(float(d["t"]), None if d.get("next") is None else float(d["next"]), bool(d.get("active")),
                   int(d.get("unacked", 0)), d.get("last_q"), d.get("hub_q"))

    def as_dict(self):
        return {"t": self.t, "next": self.next_event, "active": self.active, "unacked": self.unacked,
                "last_q": self.last_q, "hub_q": self.hub_q}


@dataclass(frozen=True)
class HubState:
    """What the hub says after each message: per sender id the highest number
    it admitted (``top``), per destination id the number of the last message
    it forwarded (``fwd``), and how many forwards are unacknowledged."""
    top: Dict[int, int] = field(default_factory=dict)
    fwd: Dict[int, int] = field(default_factory=dict)
    pending: int = 0

    @classmethod
    def from_dict(cls, d):
        return cls({int(k): int(v) for k, v in d.get("top", {}).items()},
                   {int(k): int(v) for k, v in d.get("fwd", {}).items()}, int(d.get("pending", 0)))

    def as_dict(self):
        return {"top": {str(k): v for k, v in self.top.items()}, "fwd": {str(k): v for k, v in self.fwd.items()},
                "pending": self.pending}


def _not_before(a, b):
    """Sequence number ``a`` is ``b`` or later (numbers wrap at 2^32)."""
    return a is not None and seq_diff(a, b) >= 0


class Lockstep:
    """The clock's decisions.  ``arms``: {name: robot id} of the cell;
    ``speed``: simulated s per wall s, None for as fast as the arms go;
    ``hub``: whether a hub relays the messages (False: arms alone, e.g. with
    a stand-in hub, and then only the arms' steps are awaited);
    ``min_wall_step``: wall s between two steps the pace sets (paced or idle;
    an event or ``max_step`` at speed max goes at once)."""

    def __init__(self, arms, speed=None, max_step=30.0, idle_speed=1.0, hub=True, min_wall_step=0.02):
        if speed is not None and not speed > 0:
            raise ValueError("speed must be > 0 or None (max), got %r" % (speed,))
        if not max_step > 0:
            raise ValueError("max_step must be > 0, got %r" % (max_step,))
        self.arms = dict(arms)
        self.speed, self.max_step, self.idle_speed, self.hub = speed, float(max_step), float(idle_speed), hub
        self.min_wall_step = float(min_wall_step)
        self.now = 0.0
        self._wall = None                  #: wall time of the last step
        self.ready: Dict[str, ArmReady] = {}
        self.hub_state: Optional[HubState] = None
        self.steps = 0
        self.reasons = {}                  #: steps by what set them: event, max_step, pace, idle

    def arm_ready(self, name, ready):
        if name in self.arms:
            self.ready[name] = ready

    def hub_ready(self, state):
        self.hub_state = state

    def waiting_for(self):
        """Who the clock waits for at :attr:`now` (names; empty: it may move on)."""
        late = [n for n in self.arms if n not in self.ready or self.ready[n].t < self.now - TOLERANCE_S
                or self.ready[n].unacked]
        if not self.hub:
            return late
        h = self.hub_state
        if h is None:
            return late + ["hub"]
        if h.pending:
            late.append("hub")
        for name, rid in self.arms.items():
            r = self.ready.get(name)
            if r is None:
                continue
            if r.last_q is not None and not _not_before(h.top.get(rid), r.last_q):
                late.append("hub<-%s" % name)
            if rid in h.fwd and not _not_before(r.hub_q, h.fwd[rid]):
                late.append("%s<-hub" % name)
        return late

    def next(self, wall):
        """The time to publish next at wall time ``wall`` (s), or None to keep
        :attr:`now` (someone is not done, or the pace says not yet)."""
        if self._wall is None:
            self._wall = wall
        if self.waiting_for():
            self._wall = wall          # time spent waiting for the arms does not count towards the pace
            return None
        elapsed = max(0.0, wall - self._wall)
        paced = elapsed >= self.min_wall_step        # a paced step: not more often than this
        if any(r.active for r in self.ready.values()):
            target, why = self.now + self.max_step, "max_step"
            events = [r.next_event for r in self.ready.values() if r.next_event is not None]
            if events and min(events) < target:
                target, why = max(min(events), self.now + TOLERANCE_S), "event"
            if self.speed is not None and self.now + self.speed * elapsed < target:
                target, why = (self.now + self.speed * elapsed if paced else self.now), "pace"
        else:
            target, why = (self.now + self.idle_speed * elapsed if paced else self.now), "idle"
        target = math.ceil(target * 1e9) / 1e9               # ROS time: whole ns, not before an event
        if target <= self.now + TOLERANCE_S / 2:
            return None
        self.now, self._wall = target, wall
        self.steps += 1
        self.reasons[why] = self.reasons.get(why, 0) + 1
        return target
