"""Fault injection for the hub's topics: a lossy, duplicating, reordering,
delaying channel with a seed, so that a faulty run can be repeated exactly
(given the same arrivals).  ROS-free; :mod:`ambots.ros.hub` puts one
channel on the hub's input (everything the hub receives) and one on its
output (everything it publishes), when the hub's ``~faults`` parameter
asks for it.

Each message pushed into a :class:`FaultyChannel` is, independently:

* dropped with probability ``drop``;
* otherwise delivered once, plus one more copy with probability ``dup``;
* each copy delayed by ``delay`` s, and with probability ``reorder`` by a
  further random 0..``reorder_window`` s, so later messages overtake it.

``pop_due(now)`` returns the copies whose time has come, oldest release
first.  :class:`FaultSpec` parses the parameter string
``"drop=0.2 dup=0.1 reorder=0.2 delay=0.01 seed=7"``.
"""
import heapq
import random
from dataclasses import asdict, dataclass

from ambots.errors import ConfigError

__all__ = ["FaultSpec", "FaultyChannel", "FaultCounts"]


@dataclass(frozen=True)
class FaultSpec:
    """Rates (0..1) and times (s) of the injected faults."""
    drop: float = 0.0
    dup: float = 0.0
    reorder: float = 0.0
    delay: float = 0.0
    reorder_window: float = 0.1
    seed: int = 0

    @property
    def active(self):
        return self.drop > 0 or self.dup > 0 or self.reorder > 0 or self.delay > 0

    @classmethod
    def parse(cls, text, where="~faults"):
        """``"drop=0.2 dup=0.1 reorder=0.2 delay=0.01 reorder_window=0.1
        seed=7"`` (any subset, spaces or commas) -> FaultSpec.  An empty
        string or "off" means no faults.  Bad words raise ConfigError naming
        ``where`` and the word."""
        text = (text or "").strip()
        if text.lower() in ("", "off", "none", "false", "0"):
            return cls()
        values = {}
        for word in text.replace(",", " ").split():
            key, sep, value = word.partition("=")
            if not sep or key not in cls.__dataclass_fields__:
                raise ConfigError(where, word, "expected one of %s as name=value"
                                  % ", ".join(cls.__dataclass_fields__))
            try:
                values[key] = int(value) if key == "seed" else float(value)
            except ValueError:
                raise ConfigError(where, key, "not a number: %r" % value) from None
        spec = cls(**values)
        for key in ("drop", "dup", "reorder"):
            v = getattr(spec, key)
            if not 0.0 <= v <= (0.9 if key == "drop" else 1.0):
                raise ConfigError(where, key, "must be within 0..%s, got %r" % (0.9 if key == "drop" else 1, v))
        for key in ("delay", "reorder_window"):
            v = getattr(spec, key)
            if not 0.0 <= v <= 10.0:
                raise ConfigError(where, key, "must be within 0..10 s, got %r" % v)
        return spec


@dataclass
class FaultCounts:
    """What a channel did: messages in, dropped, extra copies, delivered
    late (reordered)."""
    messages: int = 0
    dropped: int = 0
    duplicated: int = 0
    reordered: int = 0
    delivered: int = 0

    def as_dict(self):
        return asdict(self)


class FaultyChannel:
    """A channel that misbehaves as ``spec`` says (see the module docstring)."""

    def __init__(self, spec, stream=0):
        self.spec = spec
        self.rng = random.Random(int(spec.seed) * 1000003 + int(stream))
        self.counts = FaultCounts()
        self._queue = []          # (release time, order, item)
        self._order = 0

    def push(self, item, now):
        """Hand one message to the channel at time ``now`` (s)."""
        spec, rng = self.spec, self.rng
        self.counts.messages += 1
        if rng.random() < spec.drop:
            self.counts.dropped += 1
            return
        copies = 2 if rng.random() < spec.dup else 1
        self.counts.duplicated += copies - 1
        for _ in range(copies):
            t = now + spec.delay
            if rng.random() < spec.reorder:
                t += rng.uniform(0.0, spec.reorder_window)
                self.counts.reordered += 1
            heapq.heappush(self._queue, (t, self._order, item))
            self._order += 1

    def pop_due(self, now):
        """The copies due at ``now``, in release order."""
        out = []
        while self._queue and self._queue[0][0] <= now:
            out.append(heapq.heappop(self._queue)[2])
        self.counts.delivered += len(out)
        return out

    def __len__(self):
        return len(self._queue)
