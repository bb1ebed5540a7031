"""Reliable delivery (ambots.reliable): numbering, acknowledgements, retries
with capped backoff, giving up, duplicate and reordering handling, bounded
memory, and exactly-once over a lossy, reordering channel.  Fake clock."""
import random

import pytest

from ambots.protocol import HUB, MAX_U32, Ack, Pause, Start, Status, decode, encode
from ambots.reliable import Receiver, Sender, Verdict, seq_after, seq_diff, seq_seed


# --- sequence arithmetic --------------------------------------------------------

def test_sequence_numbers_wrap_and_compare_across_the_wrap():
    assert seq_after(MAX_U32) == 0 and seq_after(5, 3) == 8
    assert seq_diff(0, MAX_U32) == 1 and seq_diff(MAX_U32, 0) == -1
    assert seq_diff(10, 3) == 7 and seq_diff(3, 10) == -7


def test_seed_is_the_wall_clock_in_ms_wrapped():
    assert seq_seed(1.5) == 1500
    assert 0 <= seq_seed(1.7e9) <= MAX_U32
    assert seq_seed(1000.0) > seq_seed(999.0)


# --- Sender -------------------------------------------------------------------------

def test_sender_numbers_messages_with_its_id_and_consecutive_q():
    s = Sender(0, first_seq=MAX_U32)
    a = s.send(Start(1), destination=1, now=0.0)
    b = s.send(Pause(2, sender=7, seq=99), destination=2, now=0.0)
    assert encode(a.message) == "A1 R1 S0 Q%d" % MAX_U32
    assert (b.message.sender, b.message.seq) == (0, 0)          # S/Q replaced, Q wrapped
    assert [o.seq for o in s.pending] == [MAX_U32, 0]


def test_acks_settle_only_the_right_message_from_the_right_node():
    s = Sender(0)
    out = s.send(Start(1), destination=1, now=0.0)
    assert s.acknowledge(Ack(5, out.seq, 1)) is None             # addressed to node 5
    assert s.acknowledge(Ack(0, out.seq + 1, 1)) is None         # unknown Q
    assert s.acknowledge(Ack(0, out.seq, 2)) is None             # node 2 may not ack node 1's message
    assert s.acknowledge(Ack(0, out.seq, 2), acker=1) is out     # the authenticated acker counts
    assert s.pending == ()
    assert s.acknowledge(Ack(0, out.seq, 1)) is None             # already settled
    assert s.due(100.0) == []


def test_retries_back_off_doubling_up_to_the_cap_until_acked():
    s = Sender(0, initial_timeout=0.25, backoff=2.0, max_timeout=3.0)
    out = s.send(Start(1), destination=1, now=0.0)
    sent_at, now = [], 0.0
    while now < 13.0:
        now += 0.25                                   # exact in binary: no rounding surprises
        if s.due(now):
            sent_at.append(now)
    # timeouts 0.25, 0.5, 1, 2, then 3 (capped)
    assert sent_at == [0.25, 0.75, 1.75, 3.75, 6.75, 9.75, 12.75]
    assert out.tries == 8 and out.timeout == 3.0
    assert s.due(12.75) == []                         # nothing due twice
    s.acknowledge(Ack(0, out.seq, 1))
    assert s.due(1000.0) == []


def test_retransmission_is_the_same_text():
    s = Sender(0)
    out = s.send(Start(1), destination=1, now=0.0)
    [again] = s.due(0.2)
    assert again is out and encode(again.message) == encode(out.message)


def test_gives_up_after_max_tries_and_reports_it():
    s = Sender(0, initial_timeout=1.0, backoff=1.0, max_timeout=1.0, max_tries=3)
    out = s.send(Start(1), destination=1, now=0.0)
    given_up = []
    resent = [len(s.due(t, on_give_up=given_up.append)) for t in (1.0, 2.0, 3.0)]
    assert resent == [1, 1, 0] and given_up == [out] and s.pending == ()


def test_retries_forever_when_max_tries_is_none():
    s = Sender(0, initial_timeout=1.0, backoff=1.0, max_timeout=1.0, max_tries=None)
    out = s.send(Start(1), destination=1, now=0.0)
    for t in range(1, 1001):
        assert s.due(float(t)) == [out]
    assert out.tries == 1001


def test_an_ack_is_never_numbered():
    with pytest.raises(ValueError):
        Sender(0).send(Ack(1, 2), destination=1, now=0.0)


@pytest.mark.parametrize("kwargs", [dict(initial_timeout=0), dict(initial_timeout=3.0),
                                    dict(backoff=0.5), dict(max_tries=0)])
def test_sender_rejects_bad_timing(kwargs):
    with pytest.raises(ValueError):
        Sender(0, **kwargs)


# --- Receiver -------------------------------------------------------------------------

def test_every_numbered_message_is_acked_and_executed_once():
    r = Receiver(1)
    first = r.receive(decode("A1 R1 S0 Q7"))
    assert first.verdict is Verdict.NEW and first.execute
    assert encode(first.ack) == "A8 R0 Q7 S1"
    again = r.receive(decode("A1 R1 S0 Q7"))
    assert again.verdict is Verdict.DUPLICATE and not again.execute
    assert again.ack == first.ack                                   # duplicates are re-acked


def test_unnumbered_messages_and_acks_execute_without_an_ack():
    r = Receiver(1)
    for text in ("A1 R1", "A8 R1 Q3 S0"):
        d = r.receive(decode(text))
        assert d.verdict is Verdict.UNNUMBERED and d.execute and d.ack is None


def test_sender_defaults_to_the_s_word_then_the_hub_and_can_be_given():
    r = Receiver(1)
    assert r.receive(decode("A1 R1 Q4")).ack == Ack(HUB, 4, 1)
    assert r.receive(decode("A1 R1 S1000 Q4")).ack == Ack(1000, 4, 1)
    assert r.receive(decode("A1 R1 Q4"), sender=1000).verdict is Verdict.DUPLICATE


def test_senders_have_separate_windows():
    r = Receiver(0)
    assert r.receive(Start(1, sender=1, seq=3)).execute
    assert r.receive(Start(1, sender=2, seq=3)).execute
    assert not r.receive(Start(1, sender=2, seq=3)).execute


def test_reordering_within_the_window_executes_each_once():
    r = Receiver(1)
    order = [5, 3, 9, 4, 3, 6, 9, 8, 7, 5]
    verdicts = [r.receive(Start(1, sender=0, seq=q)).verdict for q in order]
    new, dup = Verdict.NEW, Verdict.DUPLICATE
    assert verdicts == [new, new, new, new, dup, new, dup, new, new, dup]


def test_reordering_across_the_wrap():
    r = Receiver(1)
    assert r.receive(Start(1, sender=0, seq=1)).execute
    assert r.receive(Start(1, sender=0, seq=MAX_U32)).execute      # just before 1
    assert r.receive(Start(1, sender=0, seq=0)).execute
    assert not r.receive(Start(1, sender=0, seq=MAX_U32)).execute


def test_older_than_the_window_is_acked_but_not_executed():
    r = Receiver(1, window=8)
    r.receive(Start(1, sender=0, seq=100))
    d = r.receive(Start(1, sender=0, seq=92))
    assert d.verdict is Verdict.STALE and not d.execute and d.ack == Ack(0, 92, 1)
    assert r.receive(Start(1, sender=0, seq=93)).verdict is Verdict.NEW


def test_memory_is_the_window_per_sender():
    r = Receiver(1, window=64)
    for q in range(0, 100000, 7):
        r.receive(Start(1, sender=0, seq=q))
    r.receive(Start(1, sender=0, seq=2 ** 31 - 1))                 # a far jump ahead
    assert all(w.seen.bit_length() <= 64 for w in r._windows.values())


# --- both ends over a bad channel ------------------------------------------------------

def _bad_channel(rng, tx, deliver):
    """Transmit everything ``tx`` has pending until it is all acknowledged:
    30 % of messages and of acks are lost, the rest arrive shuffled and
    sometimes twice.  ``deliver(outgoing)`` -> [(message, Delivery)]."""
    in_flight, now = list(tx.pending), 0.0
    while tx.pending:
        rng.shuffle(in_flight)
        for out in in_flight:
            for _ in range(rng.choice((1, 1, 2))):
                if rng.random() < 0.3:
                    continue
                for _m, d in deliver(out):
                    if d.ack is not None and rng.random() >= 0.3:
                        tx.acknowledge(d.ack, acker=out.destination)
        now += 0.1
        in_flight = tx.due(now)


def test_exactly_once_over_a_lossy_reordering_channel():
    """Every message takes effect exactly once over the bad channel."""
    sender, receiver = Sender(0, first_seq=MAX_U32 - 20, max_tries=None), Receiver(1)
    executed = []
    for i in range(200):
        sender.send(Status(1, 1, i, 0, 0.0), destination=1, now=0.0)

    def deliver(out):
        d = receiver.receive(out.message)
        if d.execute:
            executed.append(out.message.layer)
        return [(out.message, d)]
    _bad_channel(random.Random(4), sender, deliver)
    assert sorted(executed) == list(range(200))


def test_receiver_and_sender_survive_a_restart_through_their_snapshots():
    import json
    from ambots.protocol import Start, Resume
    from ambots.reliable import Receiver, Sender, Verdict
    rx = Receiver(2)
    tx = Sender(0, first_seq=100)
    msgs = [tx.send(Start(2), 2, 0.0).message, tx.send(Resume(2), 2, 0.0).message]
    assert rx.receive(msgs[0]).verdict is Verdict.NEW
    rx2, tx2 = Receiver(2), Sender(0, first_seq=5)
    rx2.restore(json.loads(json.dumps(rx.snapshot())))
    tx2.restore(json.loads(json.dumps(tx.snapshot())), now=1.0)
    assert rx2.receive(msgs[0]).verdict is Verdict.DUPLICATE      # executed before the restart
    assert rx2.receive(msgs[1]).verdict is Verdict.NEW
    assert [o.message for o in tx2.pending] == msgs                  # still to be acknowledged
    assert [o.message for o in tx2.due(1.0)] == msgs                 # sent again at once
    assert tx2.send(Start(2), 2, 1.0).message.seq == 102             # numbering goes on


# --- order: the B word ------------------------------------------------------------------

def test_b_names_the_previous_unacknowledged_message_to_the_same_destination():
    tx = Sender(0, first_seq=10)
    a = tx.send(Start(1), 1, 0.0).message
    other = tx.send(Start(2), 2, 0.0).message          # another destination: its own chain
    b = tx.send(Pause(1), 1, 0.0).message
    assert (a.after, other.after, b.after) == (None, None, 10)
    assert "B10" in encode(b) and decode(encode(b)) == b
    tx.acknowledge(Ack(0, 10, 1))
    assert tx.send(Start(1), 1, 0.0).message.after == 12     # 12 is still pending
    tx.acknowledge(Ack(0, 12, 1))
    c = tx.send(Pause(1), 1, 0.0).message
    assert c.after == 13
    tx.acknowledge(Ack(0, 13, 1))
    assert [o.message.after for o in tx.due(1.0) if o.seq == 14] == [None]   # settled: B dropped


def test_a_message_waits_for_its_predecessor_and_is_released_in_order():
    tx, rx = Sender(0, first_seq=5), Receiver(1)
    load, start, pause = (tx.send(m, 1, 0.0).message for m in (Status(1, 1, 0, 0, 0.0), Start(1), Pause(1)))
    [(m, d)] = rx.deliver(pause)
    assert m is pause and d.verdict is Verdict.HELD and d.ack is None and not d.execute
    assert rx.deliver(pause)[0][1].verdict is Verdict.HELD           # its duplicate too
    assert rx.deliver(start)[0][1].verdict is Verdict.HELD
    out = rx.deliver(load)
    assert [m for m, _ in out] == [load, start, pause]
    assert all(d.verdict is Verdict.NEW and d.ack is not None for _, d in out)
    assert [d.verdict for _, d in rx.deliver(start)] == [Verdict.DUPLICATE]


def test_a_predecessor_older_than_the_window_counts_as_done():
    rx = Receiver(1, window=8)
    rx.receive(Start(1, sender=0, seq=100))
    msg = Start(1, sender=0, seq=101, after=90)            # 90 is 10 behind the top: too old to tell
    assert [d.verdict for _, d in rx.deliver(msg)] == [Verdict.NEW]


def test_b_needs_q():
    from ambots.errors import ProtocolError
    with pytest.raises(ProtocolError, match="B"):
        Start(1, sender=0, after=3)
    with pytest.raises(ProtocolError, match="B"):
        decode("A1 R1 S0 B3")


def test_in_order_exactly_once_over_a_lossy_reordering_channel():
    """Two destinations share one sender's numbers; over the bad channel each
    destination executes every message of its own once, in the order sent."""
    rng = random.Random(11)
    tx = Sender(0, first_seq=MAX_U32 - 50, max_tries=None)
    rxs = {1: Receiver(1), 2: Receiver(2)}
    executed = {1: [], 2: []}
    for i in range(300):
        tx.send(Status(1, 1, i, 0, 0.0), destination=rng.choice((1, 2)), now=0.0)
    sent = {d: [o.message.layer for o in tx.pending if o.destination == d] for d in (1, 2)}

    def deliver(out):
        got = rxs[out.destination].deliver(out.message)
        executed[out.destination].extend(m.layer for m, d in got if d.execute)
        return got
    _bad_channel(rng, tx, deliver)
    assert executed == sent
