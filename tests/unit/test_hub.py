"""The communication hub's logic (ambots.hub), without ROS: routing of every
command type, acks, retries, duplicates, reordering, refusals (unknown id,
malformed, unregistered caller, spoofed sender) and progress with ETA.
The default cell: kinova = R0, ur10 = R1 (the original's ids and inbox
topics); front end = node 1000, hub = node 1001."""
import json
from dataclasses import replace

import pytest

from ambots import topics
from ambots.config import default_cell_path, load_cell
from ambots.errors import ConfigError
from ambots.hub import Hub, Post
from ambots.protocol import decode
from ambots.reliable import Receiver, Sender

FRONT_END, KINOVA, UR10, TOOL = "/front_end", "/kinova/firmware", "/ur10/firmware", "/tool"
# the original's topics, written out: the default cell must keep them
FE_IN, KINOVA_IN, UR10_IN = topics.FRONT_END_TOPIC, "/ambots/kinova_topic", "/ambots/ur_topic"
ERR = topics.ERROR_TOPIC
FIRST_Q = 100          # the hub's first sequence number in these tests


@pytest.fixture(scope="module")
def cell():
    return load_cell(default_cell_path())


@pytest.fixture
def hub(cell):
    return Hub(cell, extra_callers=[TOOL], sender=Sender(topics.HUB_ID, first_seq=FIRST_Q))


def by_topic(posts, topic):
    return [p.text for p in posts if p.topic == topic]


def errors(posts):
    return by_topic(posts, ERR)


# --- routing -----------------------------------------------------------------------------

@pytest.mark.parametrize("command", [
    "A1 R0", "A2 R0", "A3 R0", "A4 R0", "A5 R0 C3\nG1 X1 Y2 E0.1\nG1 X3", "A6 R0",
    "A7 R0 X100 Y50 Z10", "A9 R0 W1 L5", "A9 R0 W1 N120"])
def test_every_command_goes_to_its_arm_with_the_hubs_numbering(hub, command):
    posts = hub.handle(command.replace("\n", " S1000 Q7\n", 1) if "\n" in command
                       else command + " S1000 Q7", FRONT_END, now=0.0)
    assert posts[0] == Post(FE_IN, "A8 R1000 Q7 S1001")                 # ack to the sender first
    [forwarded] = by_topic(posts, KINOVA_IN)
    assert replace(decode(forwarded), sender=None, seq=None, after=None) == decode(command)
    assert (decode(forwarded).sender, decode(forwarded).seq) == (1001, FIRST_Q)
    assert len(posts) == 2


def test_the_r_word_picks_the_arm(hub):
    assert by_topic(hub.handle("A1 R1", FRONT_END, 0.0), UR10_IN) == ["A1 R1 S1001 Q%d" % FIRST_Q]


def test_arm_to_arm_command_goes_to_the_named_arm(hub):
    posts = hub.handle("A6 R1 S0 Q40", KINOVA, 0.0)
    assert posts == [Post(KINOVA_IN, "A8 R0 Q40 S1001"), Post(UR10_IN, "A6 R1 S1001 Q%d" % FIRST_Q)]


def test_a3_from_an_arm_sends_its_own_position_to_the_named_arm(hub):
    """The original's A3 R<x> from an arm: "send my position to arm x".  The
    hub hands it back to its sender (who reports X Y Z), not to arm x (who
    would report its own)."""
    posts = hub.handle("A3 R1 S0 Q40", KINOVA, 0.0)
    assert posts == [Post(KINOVA_IN, "A8 R0 Q40 S1001"), Post(KINOVA_IN, "A3 R1 S1001 Q%d" % FIRST_Q)]
    # the sender's answer, an A10 with its position, reaches arm x (and the front end)
    hub.handle("A8 R1001 Q%d S0" % FIRST_Q, KINOVA, 0.1)
    posts = hub.handle("A10 R0 T1 L3 N120 P12.5 X1 Y2 Z3 S0 Q41", KINOVA, 0.2)
    [to_ur10] = by_topic(posts, UR10_IN)
    assert decode(to_ur10).robot == 0 and decode(to_ur10).position == (1.0, 2.0, 3.0)
    # from the front end or a tool (not an arm) it still asks arm x for its position
    [to_ur10] = by_topic(hub.handle("A3 R1", TOOL, 0.3), UR10_IN)
    assert replace(decode(to_ur10), seq=None, after=None) == decode("A3 R1 S1001")


def test_unnumbered_command_is_forwarded_reliably_without_an_ack(hub):
    assert hub.handle("A6 R1", FRONT_END, 0.0) == [Post(UR10_IN, "A6 R1 S1001 Q%d" % FIRST_Q)]
    assert len(hub.sender.pending) == 1


def test_ack_to_the_hub_settles_its_message(hub):
    hub.handle("A1 R1 S1000 Q1", FRONT_END, 0.0)
    assert hub.handle("A8 R1001 Q%d S1" % FIRST_Q, UR10, 0.1) == []
    assert hub.sender.pending == () and hub.tick(10.0) == []


def test_ack_from_another_node_does_not_settle(hub):
    hub.handle("A1 R1", FRONT_END, 0.0)
    hub.handle("A8 R1001 Q%d" % FIRST_Q, KINOVA, 0.1)                     # kinova acks ur10's message
    assert len(hub.sender.pending) == 1


def test_ack_to_another_node_goes_to_its_inbox_with_the_acker(hub):
    assert hub.handle("A8 R1000 Q9", KINOVA, 0.0) == [Post(FE_IN, "A8 R1000 Q9 S0")]
    assert hub.handle("A8 R1 Q9 S0", KINOVA, 0.0) == [Post(UR10_IN, "A8 R1 Q9 S0")]


def test_status_is_consumed_and_forwarded_to_front_end_and_other_arms(hub):
    posts = hub.handle("A10 R0 T1 L3 N120 P12.5 X1 Y2 Z3 S0 Q5", KINOVA, 0.0)
    assert by_topic(posts, KINOVA_IN) == ["A8 R0 Q5 S1001"]
    [progress] = by_topic(posts, topics.PROGRESS_TOPIC)
    assert json.loads(progress)["arms"]["kinova"]["state"] == "PRINTING"
    for inbox in (FE_IN, UR10_IN):
        [status] = by_topic(posts, inbox)
        assert decode(status).robot == 0 and decode(status).layer == 3 and decode(status).sender == 1001


def test_error_report_is_published_and_forwarded_to_the_front_end(hub):
    posts = hub.handle('A11 R1 N212 S1 Q3 "nozzle temperature \\"low\\""', UR10, 4.0)
    assert errors(posts) == ['arm ur10 (R1) error at G-code line 212: nozzle temperature "low"']
    assert [decode(t).message for t in by_topic(posts, FE_IN)] == ['nozzle temperature "low"']
    assert by_topic(posts, KINOVA_IN) == []
    assert json.loads(hub.progress_json(5.0))["arms"]["ur10"]["error"] == {
        "line": 212, "message": 'nozzle temperature "low"', "time": 4.0}


def test_tool_sends_unnumbered_commands(hub):
    assert by_topic(hub.handle("A2 R0", TOOL, 0.0), KINOVA_IN) == ["A2 R0 S1001 Q%d" % FIRST_Q]


# --- retries -----------------------------------------------------------------------------

def test_forwarded_command_is_retried_with_backoff_until_acked(hub):
    [_, first] = hub.handle("A1 R1 S1000 Q1", FRONT_END, 0.0)
    retries = {t: hub.tick(t) for t in (0.19, 0.21, 0.59, 0.62, 1.40, 1.43)}   # due 0.2, 0.61, 1.42
    assert {t: len(p) for t, p in retries.items()} == {0.19: 0, 0.21: 1, 0.59: 0, 0.62: 1,
                                                       1.40: 0, 1.43: 1}
    assert all(p == [first] for p in retries.values() if p)           # the same text each time
    hub.handle("A8 R1001 Q%d S1" % FIRST_Q, UR10, 1.5)
    assert hub.tick(100.0) == []


def test_giving_up_is_reported(cell):
    hub = Hub(cell, sender=Sender(topics.HUB_ID, first_seq=FIRST_Q, max_tries=2))
    hub.handle("A1 R1", FRONT_END, 0.0)
    assert by_topic(hub.tick(0.2), UR10_IN) == ["A1 R1 S1001 Q%d" % FIRST_Q]
    assert errors(hub.tick(0.7)) == ["hub gave up delivering 'A1 R1 S1001 Q%d' to arm ur10 (R1) "
                                     "after 2 tries" % FIRST_Q]
    assert hub.sender.pending == ()


# --- duplicates and reordering -----------------------------------------------------------

def test_duplicate_is_acked_again_but_not_forwarded_again(hub):
    first = hub.handle("A1 R0 S1000 Q7", FRONT_END, 0.0)
    again = hub.handle("A1 R0 S1000 Q7", FRONT_END, 0.3)
    assert len(by_topic(first, KINOVA_IN)) == 1
    assert again == [Post(FE_IN, "A8 R1000 Q7 S1001")]
    # the same Q from another node is another message
    assert len(by_topic(hub.handle("A1 R0 S1 Q7", UR10, 0.4), KINOVA_IN)) == 1


def test_reordered_messages_are_each_forwarded_once(hub):
    forwarded = []
    for q in (7, 5, 6, 5, 7, 8):
        forwarded += by_topic(hub.handle("A1 R0 S1000 Q%d" % q, FRONT_END, 0.0), KINOVA_IN)
    assert len(forwarded) == 4


def test_a_reordered_chain_is_forwarded_in_the_order_sent(hub):
    """The front end's A1 overtakes its A5 on the way: the hub holds the A1
    (no ack, nothing forwarded) until the A5 is in, then forwards both in
    order, the A1 carrying B = the hub's number of the A5."""
    held = hub.handle("A1 R1 S1000 Q8 B7", FRONT_END, 0.0)
    assert held == []
    posts = hub.handle("A5 R1 C1 S1000 Q7\nG1 X1 Y2 E0.1", FRONT_END, 0.0)
    assert by_topic(posts, FE_IN) == ["A8 R1000 Q7 S1001", "A8 R1000 Q8 S1001"]
    load, start = (decode(t) for t in by_topic(posts, UR10_IN))
    assert (type(load).__name__, type(start).__name__) == ("LoadChunk", "Start")
    assert (load.seq, start.seq, start.after) == (FIRST_Q, FIRST_Q + 1, FIRST_Q)


def test_older_than_the_window_is_acked_and_reported(cell):
    hub = Hub(cell, receiver=Receiver(topics.HUB_ID, window=4))
    hub.handle("A1 R0 S1000 Q10", FRONT_END, 0.0)
    posts = hub.handle("A1 R0 S1000 Q2", FRONT_END, 0.0)
    assert by_topic(posts, FE_IN) == ["A8 R1000 Q2 S1001"] and by_topic(posts, KINOVA_IN) == []
    assert "Q2 is older than the last 4 numbers of node 1000" in errors(posts)[0]


# --- refusals ----------------------------------------------------------------------------

def assert_refused(posts, *words):
    """Exactly one error line, containing every word; nothing routed (an ack aside)."""
    [line] = errors(posts)
    assert line.startswith("hub refused ")
    for w in words:
        assert w in line, (w, line)
    assert all(decode(p.text).CODE == 8 for p in posts if p.topic in (KINOVA_IN, UR10_IN))
    return line


@pytest.mark.parametrize("text, word", [("A1 R9", "R9"), ("A9 R0 W9 L2", "W9")])
def test_unknown_robot_id_is_refused(hub, text, word):
    assert_refused(hub.handle(text, FRONT_END, 0.0), word, FRONT_END, repr(text),
                   "unknown robot id", "this cell has arm kinova (R0), arm ur10 (R1)")


def test_numbered_unknown_robot_id_is_acked_and_refused_once(hub):
    posts = hub.handle("A1 R9 S1000 Q3", FRONT_END, 0.0)
    assert_refused(posts, "R9")
    assert by_topic(posts, FE_IN) == ["A8 R1000 Q3 S1001"]     # received: retrying would not help
    assert hub.handle("A1 R9 S1000 Q3", FRONT_END, 0.1) == [Post(FE_IN, "A8 R1000 Q3 S1001")]


def test_unknown_node_in_an_ack_is_refused(hub):
    assert_refused(hub.handle("A8 R77 Q1", KINOVA, 0.0), "unknown node id R77")


@pytest.mark.parametrize("text, reason", [
    ("hello", "a message starts with A<code>"), ("A99 R0", "unknown command A99"),
    ("A1", "A1 needs R"), ("A1 R0 Q-4", "A1 Q"),
    ("A5 R0 S1000 Q4\nG1 X1\nA1 R1", "A-series command"),
    ("A5 R0 K1 S1000 Q4\nG1 X1", "CRC-32"), ("", "empty message")])
def test_malformed_text_is_refused_without_an_ack(hub, text, reason):
    posts = hub.handle(text, FRONT_END, 0.0)
    assert_refused(posts, "malformed", reason, FRONT_END)
    assert by_topic(posts, FE_IN) == []


def test_long_refused_text_is_cut_on_one_line(hub):
    [line] = errors(hub.handle("A5 R9\n" + "G1 X1\n" * 1000, FRONT_END, 0.0))
    assert "\n" not in line and len(line) < 400


def test_unregistered_caller_is_refused(hub):
    posts = hub.handle("A1 R0 S1000 Q1", "/intruder", 0.0)
    assert_refused(posts, "/intruder", "not a registered node", FRONT_END, KINOVA)
    assert len(posts) == 1                                            # no ack either


@pytest.mark.parametrize("text, caller, words", [
    ("A1 R0 S1 Q1", FRONT_END, ["S1 claims node 1", "front end, node 1000"]),
    ("A10 R1 T1 L1 N1 P1 S1 Q1", KINOVA, ["S1 claims node 1", "arm kinova (R0)"]),
    ("A8 R1001 Q%d S1" % FIRST_Q, KINOVA, ["S1 claims node 1"]),
    ("A1 R0 S1000", TOOL, ["tool /tool", "neither S nor Q"]),
    ("A1 R0 Q5", TOOL, ["neither S nor Q"])])
def test_spoofed_sender_is_refused_without_an_ack(hub, text, caller, words):
    posts = hub.handle(text, caller, 0.0)
    assert_refused(posts, caller, *words)
    assert len(posts) == 1


@pytest.mark.parametrize("text, caller", [
    ("A10 R1 T1 L1 N1 P1 S0 Q1", KINOVA),          # status of another arm
    ("A11 R0 N0 S1000 Q1 \"x\"", FRONT_END),        # the front end is not an arm
    ("A10 R0 T1 L1 N1 P1", TOOL)])
def test_an_arm_reports_only_about_itself(hub, text, caller):
    assert_refused(hub.handle(text, caller, 0.0), "reports only about itself")
    assert json.loads(hub.progress_json(0.0))["arms"]["ur10"]["state"] == "UNKNOWN"


def test_a_tool_cannot_acknowledge(hub):
    hub.handle("A1 R0", FRONT_END, 0.0)
    assert_refused(hub.handle("A8 R1001 Q%d" % FIRST_Q, TOOL, 0.1), "cannot acknowledge")
    assert len(hub.sender.pending) == 1


def test_hub_keeps_routing_after_refusals(hub):
    for text, caller in (("A1 R9", FRONT_END), ("junk", FRONT_END), ("A1 R0", "/intruder"),
                         ("A1 R0 S1", FRONT_END)):
        hub.handle(text, caller, 0.0)
    assert by_topic(hub.handle("A1 R0 S1000 Q1", FRONT_END, 0.0), KINOVA_IN) == [
        "A1 R0 S1001 Q%d" % FIRST_Q]


def test_an_arm_id_equal_to_the_front_ends_is_a_config_error(cell):
    bad = replace(cell, arms=(replace(cell.arms[0], id=topics.FRONT_END_ID),) + cell.arms[1:])
    with pytest.raises(ConfigError, match="front end"):
        Hub(bad)


# --- progress ----------------------------------------------------------------------------

def progress(hub, now):
    return json.loads(hub.progress_json(now))


def status(hub, arm_id, caller, now, percent, state=1, layer=0, line=0):
    hub.handle("A10 R%d T%d L%d N%d P%g" % (arm_id, state, layer, line, percent), caller, now)


def test_progress_lists_every_arm_even_before_any_report(hub):
    p = progress(hub, 3.0)
    assert p["stamp"] == 3.0 and set(p["arms"]) == {"kinova", "ur10"}
    assert p["arms"]["ur10"] == {"id": 1, "state": "UNKNOWN", "layer": None, "line": None,
                                 "percent": None, "eta_s": None, "updated": None,
                                 "position": None, "error": None}


def test_progress_aggregates_both_arms_with_eta(hub):
    status(hub, 0, KINOVA, 100.0, 10.0, layer=1, line=50)
    status(hub, 1, UR10, 100.0, 0.0)
    assert progress(hub, 100.0)["arms"]["kinova"]["eta_s"] is None      # no rate yet
    status(hub, 0, KINOVA, 110.0, 30.0, layer=4, line=300)              # 2 %/s
    status(hub, 1, UR10, 120.0, 20.0)                                    # 1 %/s
    arms = progress(hub, 120.0)["arms"]
    assert arms["kinova"] == {"id": 0, "state": "PRINTING", "layer": 4, "line": 300,
                              "percent": 30.0, "eta_s": 25.0, "updated": 110.0,
                              "position": None, "error": None}
    assert arms["ur10"]["eta_s"] == 80.0
    assert progress(hub, 200.0)["arms"]["kinova"]["eta_s"] == 0.0        # counts down, not below 0


def test_eta_freezes_when_paused_is_zero_when_done_and_restarts_with_a_new_job(hub):
    status(hub, 0, KINOVA, 0.0, 0.0)
    status(hub, 0, KINOVA, 10.0, 50.0, state=2)                         # paused
    assert progress(hub, 30.0)["arms"]["kinova"]["eta_s"] == 10.0
    status(hub, 0, KINOVA, 40.0, 100.0, state=4)
    assert progress(hub, 40.0)["arms"]["kinova"]["eta_s"] == 0.0
    status(hub, 0, KINOVA, 50.0, 5.0)                                    # a new job
    status(hub, 0, KINOVA, 60.0, 10.0)
    assert progress(hub, 60.0)["arms"]["kinova"]["eta_s"] == 180.0


def test_status_with_position_is_in_the_progress(hub):
    hub.handle("A10 R1 T0 L0 N0 P0 X1.5 Y-2 Z3", UR10, 0.0)
    assert progress(hub, 0.0)["arms"]["ur10"]["position"] == [1.5, -2.0, 3.0]


# --- restart ------------------------------------------------------------------------------

def test_a_restarted_hub_forwards_what_the_old_one_acknowledged_once_under_the_same_numbers(cell, hub):
    posts = hub.handle("A5 R1 C1 S1000 Q7\nG1 X1 Y2 E0.1", FRONT_END, 0.0)
    [fwd] = by_topic(posts, UR10_IN)
    snap = json.loads(json.dumps(hub.snapshot()))          # what the ROS layer saved before publishing
    # the old hub dies; the forward it published may or may not have arrived
    new = Hub(cell, extra_callers=[TOOL], sender=Sender(topics.HUB_ID, first_seq=5))
    new.restore(snap, now=10.0)
    again = new.handle("A5 R1 C1 S1000 Q7\nG1 X1 Y2 E0.1", FRONT_END, 10.0)   # the front end's retry
    assert by_topic(again, FE_IN) == ["A8 R1000 Q7 S1001"] and by_topic(again, UR10_IN) == []   # not twice
    assert by_topic(new.tick(10.0), UR10_IN) == [fwd]       # the unacknowledged forward, same Q
    start = decode(by_topic(new.handle("A1 R1 S1000 Q8", FRONT_END, 10.0), UR10_IN)[0])
    assert (start.seq, start.after) == (FIRST_Q + 1, FIRST_Q)   # numbering goes on, in order after the A5
