"""Reliable delivery over lossy topics: sequence numbers, acknowledgements,
retries and duplicate suppression, shared by every node that speaks the
A-series protocol (hub, firmware, front end).

- :class:`Sender` numbers outgoing messages (``S<node> Q<seq>``), keeps each
  until an A8 acknowledges it, and :meth:`Sender.due` says what to transmit
  again: the timeout starts at ``initial_timeout`` and is multiplied by
  ``backoff`` after every try, up to ``max_timeout``; after ``max_tries``
  transmissions it gives up (``None``: never).
- :class:`Receiver` answers every numbered message with an A8 (duplicates
  too) and says whether to execute it, so that each (sender, Q) takes effect
  at most once.  Per sender it keeps the highest Q seen and a bitmap of the
  ``window`` numbers below it (the anti-replay window of IPsec, RFC 4303
  3.4.3): messages may arrive in any order within the window, and memory is
  ``window`` bits per sender.  A number older than the window cannot be
  told apart from a duplicate; it is acknowledged but not executed
  (:attr:`Verdict.STALE`), and the caller should report it.
- Order: the sender writes ``B<seq>`` on a message when its previous message
  to the same destination is still unacknowledged (retransmissions drop the
  B once that one is settled); :meth:`Receiver.deliver` holds such a message
  (:attr:`Verdict.HELD`, no A8) until (sender, B) has been admitted, then
  releases it.  Each sender's messages to one destination therefore take
  effect in sending order, exactly once, under loss, duplication and
  reordering; a held message costs nothing to the sender but waiting.

Q wraps at 2**32; numbers are compared in serial-number arithmetic (RFC 1982).
No clock is read here: every call that depends on time takes ``now``
(seconds, from whatever clock the caller uses consistently).
"""
from dataclasses import dataclass, replace
from enum import Enum
from typing import Any, Optional

from ambots.protocol import HUB, MAX_U32, Ack

SEQ_MODULUS = MAX_U32 + 1
_HALF = SEQ_MODULUS // 2


def seq_after(seq, n=1):
    """The sequence number ``n`` after ``seq`` (wrapping)."""
    return (seq + n) % SEQ_MODULUS


def seq_diff(a, b):
    """``a - b`` in serial-number arithmetic, in [-2**31, 2**31)."""
    return (a - b + _HALF) % SEQ_MODULUS - _HALF


def seq_seed(wall_time):
    """A first Q for a node starting at ``wall_time`` (s since the epoch):
    the wall clock in ms.  A restarted node then numbers above its
    predecessor (if that one sent less than one message per ms on average
    and started less than 24 days earlier), so receivers that still remember
    the old numbers do not take the new messages for duplicates."""
    return int(wall_time * 1000) % SEQ_MODULUS


@dataclass
class Outgoing:
    """A numbered message waiting for its acknowledgement."""
    message: Any          #: the message as transmitted (its ``sender`` and ``seq`` set)
    destination: int      #: node id that must acknowledge it
    tries: int            #: transmissions so far
    timeout: float        #: s to wait after the last transmission
    due: float            #: when to transmit again (the caller's clock)

    @property
    def seq(self):
        return self.message.seq


class Sender:
    """Numbers the messages node ``node_id`` sends and retries them until
    acknowledged.  Memory: one :class:`Outgoing` per unacknowledged message,
    each dropped after ``max_tries`` transmissions (keep it finite for bounded
    memory when a destination may be gone for good)."""

    def __init__(self, node_id, first_seq=0, initial_timeout=0.2, backoff=2.0, max_timeout=2.0,
                 max_tries=None):
        if not 0 < initial_timeout <= max_timeout:
            raise ValueError("need 0 < initial_timeout <= max_timeout, got %r, %r"
                             % (initial_timeout, max_timeout))
        if backoff < 1:
            raise ValueError("backoff must be >= 1, got %r" % backoff)
        if max_tries is not None and max_tries < 1:
            raise ValueError("max_tries must be >= 1 or None (retry forever), got %r" % max_tries)
        self.node_id = node_id
        self.initial_timeout, self.backoff, self.max_timeout = initial_timeout, backoff, max_timeout
        self.max_tries = max_tries
        self._next_seq = first_seq % SEQ_MODULUS
        self._pending = {}       # seq -> Outgoing, in sending order
        self._last_to = {}       # destination -> seq of the last message sent to it

    @property
    def pending(self):
        """The unacknowledged messages, oldest first."""
        return tuple(self._pending.values())

    @property
    def last_seq(self):
        """The number of the last message numbered (None: none yet)."""
        return seq_after(self._next_seq, -1) if self._last_to else None

    def last_to(self, destination):
        """The number of the last message sent to ``destination`` (None: none)."""
        return self._last_to.get(destination)

    def send(self, message, destination, now):
        """Number ``message`` (S = this node, Q = the next number), keep it
        until node ``destination`` acknowledges it, and return the
        :class:`Outgoing` whose ``message`` the caller transmits now."""
        if isinstance(message, Ack):
            raise ValueError("an A8 is never numbered nor retried")
        seq = self._next_seq
        self._next_seq = seq_after(seq)
        before = self._last_to.get(destination)
        after = before if before in self._pending else None
        out = Outgoing(replace(message, sender=self.node_id, seq=seq, after=after), destination, 1,
                       self.initial_timeout, now + self.initial_timeout)
        self._pending[seq] = out
        self._last_to[destination] = seq
        return out

    def acknowledge(self, ack, acker=None):
        """Settle the message that the A8 ``ack`` acknowledges.  ``acker`` is
        the node id the ack really comes from (default: its S word); an ack
        from a node other than the message's destination does not count.
        Returns the settled :class:`Outgoing`, or None (not addressed to this
        node, unknown or already settled Q, wrong acker)."""
        if ack.robot != self.node_id:
            return None
        acker = ack.sender if acker is None else acker
        out = self._pending.get(ack.acked_seq)
        if out is None or (acker is not None and acker != out.destination):
            return None
        del self._pending[ack.acked_seq]
        return out

    def snapshot(self):
        """JSON-able state: the next number and the unacknowledged messages
        (as text), so that a restarted node goes on where it stopped."""
        from ambots.protocol import encode
        return {"next": self._next_seq,
                "pending": [[encode(o.message), o.destination, o.tries] for o in self._pending.values()]}

    def restore(self, snap, now):
        """Undo a restart: continue numbering after ``snap``'s and send its
        unacknowledged messages again (due at once, same numbers)."""
        from ambots.protocol import decode
        self._next_seq = int(snap["next"]) % SEQ_MODULUS
        self._pending, self._last_to = {}, {}
        for text, dest, tries in snap["pending"]:
            msg = decode(text)
            self._pending[msg.seq] = Outgoing(msg, int(dest), int(tries), self.initial_timeout, now)
            self._last_to[int(dest)] = msg.seq

    def due(self, now, on_give_up=None):
        """The messages to transmit again at ``now`` (their tries, timeout
        and due time already advanced).  A message whose last try has timed
        out after ``max_tries`` transmissions is dropped and passed to
        ``on_give_up(outgoing)``."""
        resend = []
        for seq, out in list(self._pending.items()):
            if out.due > now:
                continue
            if self.max_tries is not None and out.tries >= self.max_tries:
                del self._pending[seq]
                if on_give_up is not None:
                    on_give_up(out)
                continue
            out.tries += 1
            out.timeout = min(out.timeout * self.backoff, self.max_timeout)
            out.due = now + out.timeout
            if out.message.after is not None and out.message.after not in self._pending:
                out.message = replace(out.message, after=None)    # its predecessor is settled
            resend.append(out)
        return resend


class Verdict(Enum):
    """What a receiver does with one incoming message."""
    NEW = "new"                 #: first time: acknowledge and execute
    DUPLICATE = "duplicate"     #: executed before: acknowledge again, do not execute
    STALE = "stale"             #: older than the window: acknowledge, do not execute, report
    HELD = "held"               #: its predecessor (B) is not here yet: no A8, released later
    UNNUMBERED = "unnumbered"   #: no Q (original design, or an A8): execute, no acknowledgement


@dataclass(frozen=True)
class Delivery:
    """A receiver's answer: the verdict and the A8 to send back (or None)."""
    verdict: Verdict
    ack: Optional[Ack]

    @property
    def execute(self):
        """Whether the message should take effect now."""
        return self.verdict in (Verdict.NEW, Verdict.UNNUMBERED)


class _Window:
    """Highest Q seen from one sender, and bit i set = Q ``top - i`` seen."""
    __slots__ = ("top", "seen")

    def __init__(self, top):
        self.top, self.seen = top, 1


class Receiver:
    """Acknowledges and deduplicates the numbered messages node ``node_id``
    receives.  One window of ``window`` bits per sender id: the caller bounds
    the senders (e.g. to the registered nodes)."""

    def __init__(self, node_id, window=4096):
        if window < 1:
            raise ValueError("window must be >= 1, got %r" % window)
        self.node_id, self.window = node_id, window
        self._windows = {}      # sender id -> _Window
        self._held = {}         # sender id -> {B: message waiting for (sender, B)}

    def receive(self, message, sender=None):
        """The :class:`Delivery` for ``message`` alone, ignoring its B word
        (no holding).  ``sender`` is the node id it really comes from
        (default: its S word, else the hub, as in
        :func:`ambots.protocol.ack`); the A8 is addressed to it."""
        seq = getattr(message, "seq", None)       # an A8 has no seq: never acknowledged
        if seq is None:
            return Delivery(Verdict.UNNUMBERED, None)
        if sender is None:
            sender = HUB if message.sender is None else message.sender
        return Delivery(self._admit(sender, seq), Ack(sender, seq, self.node_id))

    def deliver(self, message, sender=None):
        """What to do with ``message`` and with the held messages it
        releases: a list of ``(message, Delivery)`` in execution order.  The
        first is ``message`` itself, :attr:`Verdict.HELD` (no A8) if it
        names a predecessor (B) not admitted yet; each message admitted
        releases the one held behind it, and so on down the chain."""
        seq = getattr(message, "seq", None)
        if seq is None:
            return [(message, Delivery(Verdict.UNNUMBERED, None))]
        if sender is None:
            sender = HUB if message.sender is None else message.sender
        after = getattr(message, "after", None)
        if after is not None and not self._seen(sender, seq) and not self._seen(sender, after):
            held = self._held.setdefault(sender, {})
            if len(held) >= self.window:          # bounded: the oldest waits for its retry
                del held[next(iter(held))]
            held[after] = message
            return [(message, Delivery(Verdict.HELD, None))]
        out = [(message, self.receive(message, sender))]
        held = self._held.get(sender)
        while held:
            nxt = held.pop(out[-1][0].seq, None)
            if nxt is None:
                break
            out.append((nxt, self.receive(nxt, sender)))
        return out

    def top(self, sender):
        """The highest number admitted from ``sender`` (None: nothing yet)."""
        w = self._windows.get(sender)
        return None if w is None else w.top

    def _seen(self, sender, seq):
        """Whether (sender, seq) was admitted, or is too old to tell (then
        it counts as done, like a STALE message)."""
        w = self._windows.get(sender)
        if w is None:
            return False
        behind = -seq_diff(seq, w.top)
        if behind < 0:
            return False
        return behind >= self.window or bool(w.seen & (1 << behind))

    def snapshot(self):
        """JSON-able state: per sender the highest number and the bit mask of
        the numbers seen (hex), so that a restarted node still recognises
        what it executed before."""
        return {str(k): [w.top, "%x" % w.seen] for k, w in self._windows.items()}

    def restore(self, snap):
        self._windows = {}
        for k, (top, seen) in snap.items():
            w = _Window(int(top))
            w.seen = int(seen, 16)
            self._windows[int(k)] = w

    def _admit(self, sender, seq):
        w = self._windows.get(sender)
        if w is None:
            self._windows[sender] = _Window(seq)
            return Verdict.NEW
        ahead = seq_diff(seq, w.top)
        if ahead > 0:
            w.seen = 1 if ahead >= self.window else ((w.seen << ahead) | 1) & ((1 << self.window) - 1)
            w.top = seq
            return Verdict.NEW
        if -ahead >= self.window:
            return Verdict.STALE
        bit = 1 << -ahead
        if w.seen & bit:
            return Verdict.DUPLICATE
        w.seen |= bit
        return Verdict.NEW
