"""The communication hub's logic: who may talk, where each A-series message
goes, reliable forwarding, and the cell's progress.  ROS-free: a message
comes in as (text, caller, now) and what to publish goes out as
:class:`Post` (topic, text); the ROS wrapper is ``ambots.ros.hub``.

One incoming message (:meth:`Hub.handle`):

1. the caller (ROS node name) must be a registered node -- an arm's firmware
   (``topics.arm_node``) or the front end -- or one of the ``extra_callers``
   (tools: no node id, no inbox, so they send neither S nor Q);
2. the text must decode (:func:`ambots.protocol.decode`);
3. an S word must be the caller's own node id (no spoofing);
4. a numbered message is acknowledged (A8) to the caller's inbox, duplicates
   too, and takes effect at most once (:class:`ambots.reliable.Receiver`);
5. routing:

   - A1..A7, A9: to arm R (A9's W must be an arm too), forwarded with the
     hub's own numbering (S1001, Q from :class:`ambots.reliable.Sender`) and
     retried by :meth:`Hub.tick` until acknowledged; except an A3 R<x> from
     another arm, which means what it meant in the original: "send my
     position to arm x", so it goes back to its sender, whose A10 with its
     position then reaches arm x;
   - A8 R1001: settles one of the hub's messages; A8 R<n>: to node n's inbox as is;
   - A10 / A11 (an arm about itself only): progress / a line on the error
     topic, then forwarded like a command -- A10 to the front end and to the
     other arms (their A9 barriers and A3 position replies need it), A11 to
     the front end.

A refusal is one line on ``topics.ERROR_TOPIC`` naming the caller, the text
and the reason; the hub goes on.

Restart: the registry comes from the cell and the progress from the arms'
next A10s.  What exactly-once needs -- the duplicate windows and the
forwards not yet acknowledged -- is :meth:`Hub.snapshot`; a wrapper that
saves it before it publishes what :meth:`Hub.handle` returned (the ROS one
does, ``~state_dir``) can :meth:`Hub.restore` it after a crash: nothing the
old hub acknowledged is lost, nothing is forwarded under a number the arms
have seen for something else.  A hub that starts without a snapshot seeds
its Sender with :func:`ambots.reliable.seq_seed` so that the arms do not
take its numbers for duplicates.
"""
import json
from dataclasses import dataclass, field, replace
from typing import Optional, Tuple

from ambots import topics
from ambots.errors import ConfigError, ProtocolError
from ambots.protocol import Ack, ArmState, ErrorReport, SendPosition, Status, WaitFor, decode, encode, printable
from ambots.reliable import Receiver, Sender, Verdict

#: longest excerpt of a refused text quoted on the error topic (characters)
EXCERPT = 160


@dataclass(frozen=True)
class Post:
    """One std_msgs/String the hub publishes."""
    topic: str
    text: str


@dataclass(frozen=True)
class Endpoint:
    """A node that may talk to the hub.  Tools have ``id`` and ``inbox`` None."""
    id: Optional[int]
    caller: str           #: ROS node name, as in the message's callerid
    inbox: Optional[str]  #: topic the hub publishes to for this node
    label: str            #: for humans, e.g. "arm ur10 (R2)"


class _Refused(Exception):
    """A message the hub will not route; the argument is the reason."""


class Registry:
    """The nodes of a cell: arms (id and names from the cell), the front end
    (``topics.FRONT_END_ID``) and tools (``extra_callers``)."""

    def __init__(self, cell, extra_callers=()):
        self.arms = {a.id: Endpoint(a.id, topics.arm_node(a.name), topics.arm_topic(a),
                                    "arm %s (R%d)" % (a.name, a.id)) for a in cell.arms}
        if topics.FRONT_END_ID in self.arms:
            raise ConfigError(cell.path, "arms", "robot id %d is the front end's node id"
                              % topics.FRONT_END_ID)
        self.front_end = Endpoint(topics.FRONT_END_ID, topics.FRONT_END_NODE,
                                  topics.FRONT_END_TOPIC, "front end")
        self.nodes = {**self.arms, topics.FRONT_END_ID: self.front_end}
        self._by_caller = {e.caller: e for e in self.nodes.values()}
        for name in extra_callers:
            self._by_caller.setdefault(name, Endpoint(None, name, None, "tool %s" % name))

    @property
    def inboxes(self):
        """Every topic the hub delivers to."""
        return [e.inbox for e in self.nodes.values()]

    def caller(self, name):
        """The endpoint of ROS node ``name``; refuses an unregistered one."""
        try:
            return self._by_caller[name]
        except KeyError:
            raise _Refused("caller %s is not a registered node (registered: %s)"
                           % (name, ", ".join(sorted(self._by_caller)))) from None

    def arm(self, robot_id, letter="R"):
        """The arm with robot id ``robot_id``; refuses an unknown id."""
        try:
            return self.arms[robot_id]
        except KeyError:
            raise _Refused("unknown robot id %s%d (this cell has %s)" % (
                letter, robot_id, ", ".join(e.label for e in self.arms.values()))) from None

    def node(self, node_id):
        """The registered node with id ``node_id`` (arm or front end)."""
        try:
            return self.nodes[node_id]
        except KeyError:
            raise _Refused("unknown node id R%d (nodes: %s)" % (
                node_id, ", ".join("%d %s" % (i, e.label) for i, e in self.nodes.items()))) from None


@dataclass
class ArmProgress:
    """What the hub knows about one arm, from its A10s and A11s.  The ETA
    is the remaining percent over the average rate since the current job's
    first report (a new job: the percent went down, or the arm was idle)."""
    name: str
    id: int
    state: Optional[ArmState] = None
    layer: Optional[int] = None
    line: Optional[int] = None
    percent: Optional[float] = None
    position: Optional[Tuple[float, float, float]] = None
    updated: Optional[float] = None
    error: Optional[dict] = None
    clock: Optional[float] = None           #: the arm's clock (M) at its last report
    _eta_at_update: Optional[float] = field(default=None, init=False, repr=False)
    #: (time, percent) the rate is measured from
    _anchor: Optional[Tuple[float, float]] = field(default=None, init=False, repr=False)

    def update(self, status, now):
        """Take in the A10 ``status`` received at ``now`` (one older, by the
        arm's clock M, than the last is a late copy: ignored)."""
        if status.clock is not None and self.clock is not None and status.clock < self.clock:
            return
        if status.clock is not None:
            self.clock = status.clock
        if self.percent is None or status.percent < self.percent or status.state == ArmState.IDLE:
            self._anchor = (now, status.percent)
        self.state, self.layer, self.line = status.state, status.layer, status.line
        self.percent, self.position, self.updated = status.percent, status.position, now
        self._eta_at_update = self._estimate_eta(now)

    def record_error(self, report, now):
        """Take in the A11 ``report`` received at ``now``."""
        self.error = {"line": report.line, "message": report.message, "time": now}

    def _estimate_eta(self, now):
        if self.state == ArmState.DONE:
            return 0.0
        t0, p0 = self._anchor
        if now <= t0 or self.percent <= p0:
            return None
        return (100.0 - self.percent) * (now - t0) / (self.percent - p0)

    def eta(self, now):
        """Seconds until done, or None while unknown; counts down between
        reports while printing."""
        if self._eta_at_update is None or self.state != ArmState.PRINTING:
            return self._eta_at_update
        return max(0.0, self._eta_at_update - (now - self.updated))

    def as_dict(self, now):
        return {"id": self.id, "state": self.state.name if self.state is not None else "UNKNOWN",
                "layer": self.layer, "line": self.line, "percent": self.percent,
                "eta_s": self.eta(now), "updated": self.updated,
                "position": list(self.position) if self.position else None, "error": self.error}


class Hub:
    """Routes A-series messages between the nodes of ``cell`` (see the
    module docstring).  ``sender`` / ``receiver`` default to a Sender and a
    Receiver of node ``topics.HUB_ID`` with default timing.  Every method
    that depends on time takes ``now`` (s)."""

    def __init__(self, cell, extra_callers=(), sender=None, receiver=None):
        self.registry = Registry(cell, extra_callers)
        self.sender = sender if sender is not None else Sender(topics.HUB_ID)
        self.receiver = receiver if receiver is not None else Receiver(topics.HUB_ID)
        self.progress = {a.id: ArmProgress(a.name, a.id) for a in cell.arms}

    def snapshot(self):
        """JSON-able state that a restarted hub needs to stay exactly-once:
        the duplicate windows and the forwards not yet acknowledged (the
        progress is rebuilt from the arms' next reports)."""
        return {"receiver": self.receiver.snapshot(), "sender": self.sender.snapshot()}

    def restore(self, snap, now):
        """Continue from :meth:`snapshot` ``snap``: same duplicate windows,
        numbering after the old hub's, its unacknowledged forwards due at
        ``now``."""
        self.receiver.restore(snap["receiver"])
        self.sender.restore(snap["sender"], now)

    def handle(self, text, caller, now):
        """The posts answering ``text`` published by ROS node ``caller``."""
        try:
            src = self.registry.caller(caller)
            msg = decode(text)
            _check_identity(msg, src)
        except _Refused as exc:
            return [_refusal(text, caller, str(exc))]
        except ProtocolError as exc:
            return [_refusal(text, caller, "malformed: " + exc.message)]
        posts = []
        for m, delivery in self.receiver.deliver(msg, src.id):     # m and what it releases, in order
            m_text = text if m is msg else encode(m)
            if delivery.ack:
                posts.append(Post(src.inbox, encode(delivery.ack)))
            if delivery.verdict is Verdict.STALE:
                reason = ("Q%d is older than the last %d numbers of node %d: it may have been "
                          "executed already" % (m.seq, self.receiver.window, src.id))
                posts.append(_refusal(m_text, caller, reason))
            if delivery.execute:
                try:
                    posts += self._route(m, src, now)
                except _Refused as exc:
                    posts.append(_refusal(m_text, caller, str(exc)))
        return posts

    def tick(self, now):
        """Retransmissions due at ``now``, and a line on the error topic for
        each message given up."""
        abandoned = []
        posts = [Post(self.registry.nodes[out.destination].inbox, encode(out.message))
                 for out in self.sender.due(now, on_give_up=abandoned.append)]
        posts += [Post(topics.ERROR_TOPIC, "hub gave up delivering %s to %s after %d tries" % (
            _excerpt(encode(out.message)), self.registry.nodes[out.destination].label, out.tries))
            for out in abandoned]
        return posts

    def progress_json(self, now):
        """The progress of every arm, one JSON object:
        ``{"stamp": now, "arms": {name: {id, state, layer, line, percent,
        eta_s, updated, position, error}}}``."""
        return json.dumps({"stamp": now, "arms": {p.name: p.as_dict(now)
                                                  for p in self.progress.values()}})

    def _route(self, msg, src, now):
        if isinstance(msg, Ack):
            return self._on_ack(msg, src)
        if isinstance(msg, (Status, ErrorReport)):
            return self._on_report(msg, src, now)
        target = self.registry.arm(msg.robot)
        if isinstance(msg, WaitFor):
            self.registry.arm(msg.other, "W")
        if isinstance(msg, SendPosition) and src.id in self.registry.arms and src.id != msg.robot:
            # the original's A3 from an arm: "send MY position to arm R"; the
            # sender reports it (A10 with X Y Z), which reaches arm R with the others
            target = src
        return [self._forward(msg, target, now)]

    def _on_ack(self, ack, src):
        if src.id is None:
            raise _Refused("a tool has no node id: it cannot acknowledge")
        if ack.robot == topics.HUB_ID:
            self.sender.acknowledge(ack, acker=src.id)
            return []
        return [Post(self.registry.node(ack.robot).inbox, encode(replace(ack, sender=src.id)))]

    def _on_report(self, report, src, now):
        if src.id not in self.registry.arms or report.robot != src.id:
            raise _Refused("A%d R%d from %s: an arm reports only about itself"
                           % (report.CODE, report.robot, src.label))
        arm = self.progress[src.id]
        if isinstance(report, Status):
            arm.update(report, now)
            posts = [Post(topics.PROGRESS_TOPIC, self.progress_json(now))]
            readers = [e for e in self.registry.nodes.values() if e.id != src.id]
        else:
            arm.record_error(report, now)
            posts = [Post(topics.ERROR_TOPIC, "%s error at G-code line %d: %s"
                          % (src.label, report.line, printable(report.message)))]
            readers = [self.registry.front_end]
        return posts + [self._forward(report, e, now) for e in readers]

    def _forward(self, msg, target, now):
        out = self.sender.send(msg, target.id, now)
        return Post(target.inbox, encode(out.message))


def _check_identity(msg, src):
    """Refuse a message whose S word is not its caller's node id, and S or Q
    from a tool (it has no node id to claim nor inbox for the A8)."""
    if src.id is None:
        if msg.sender is not None or getattr(msg, "seq", None) is not None:
            raise _Refused("%s has no node id nor inbox: it sends neither S nor Q" % src.label)
    elif msg.sender is not None and msg.sender != src.id:
        raise _Refused("S%d claims node %d, but the caller is %s, node %d"
                       % (msg.sender, msg.sender, src.label, src.id))


def _excerpt(text):
    """``text`` (anything: a refused message need not be a str) quoted on one
    line, cut to about :data:`EXCERPT` characters."""
    if not isinstance(text, str):
        return _cut(repr(text))
    return repr(text) if len(text) <= EXCERPT else repr(text[:EXCERPT]) + "..."


def _cut(text, n=EXCERPT):
    return text if len(text) <= n else text[:n] + "..."


def _refusal(text, caller, reason):
    # the reason quotes the offending word: cut it too (a 10 kB word stays a short line)
    return Post(topics.ERROR_TOPIC, "hub refused %s from %s: %s"
                % (_excerpt(text), caller, _cut(reason, 2 * EXCERPT)))
