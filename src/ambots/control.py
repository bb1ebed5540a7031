"""An operator's control of a running print: pause, resume or stop one arm
or all (ROS-free; used by ``python -m ambots ctl`` and the menu's progress
view).

- ``pause``: A2, the arm stops at the end of the G-code line it is on;
- ``stop``: A12, the arm brakes at once (to the first waypoint it can rest
  on within its acceleration limits) and is PAUSED, so the job is kept;
- ``resume``: A6, a paused or stopped arm goes on from where it rests.

An arm that another waits for at a barrier stays where it is while paused,
so the other keeps waiting: pausing never lets an arm into another's space.
"""
from ambots.errors import AmbotsError
from ambots.protocol import ArmState, Pause, Resume, Stop

#: action -> the A-series command it sends
ACTIONS = {"pause": Pause, "resume": Resume, "stop": Stop}
#: the menu's keys
KEYS = {"p": "pause", "r": "resume", "s": "stop"}
#: states in which an arm has obeyed (or has nothing to obey: idle, done, failed)
_SETTLED = {
    "pause": {ArmState.PAUSED, ArmState.IDLE, ArmState.DONE, ArmState.ERROR},
    "stop": {ArmState.PAUSED, ArmState.IDLE, ArmState.DONE, ArmState.ERROR},
    "resume": {ArmState.PRINTING, ArmState.WAITING, ArmState.IDLE, ArmState.DONE, ArmState.ERROR},
}


class ControlError(AmbotsError):
    """A control request that names no action or no arm of the cell."""


def targets(cell, target="all"):
    """The arms ``target`` names: ``all``, an arm's name or its robot id."""
    target = str(target).strip() or "all"
    if target == "all":
        return list(cell.arms)
    for arm in cell.arms:
        if target in (arm.name, str(arm.id), "R%d" % arm.id):
            return [arm]
    raise ControlError("no arm %r in cell %s (arms: %s, or all)" % (
        target, cell.name, ", ".join("%s (R%d)" % (a.name, a.id) for a in cell.arms)))


def commands(cell, action, target="all"):
    """The messages (unnumbered) that carry out ``action`` on ``target``."""
    try:
        make = ACTIONS[action]
    except KeyError:
        raise ControlError("unknown action %r (pause, resume or stop)" % (action,)) from None
    return [make(arm.id) for arm in targets(cell, target)]


def parse_key_line(cell, line):
    """A line typed in the progress view (``p``, ``s ur10``, ``r all``,
    ``pause 1``) -> (action, messages); None for an empty line.  Raises
    :class:`ControlError` saying what is expected."""
    words = line.split()
    if not words:
        return None
    action = KEYS.get(words[0].lower(), words[0].lower())
    if action not in ACTIONS or len(words) > 2:
        raise ControlError("%r: type p, r or s (pause, resume, stop), then an arm or nothing for all"
                           % line.strip()[:40])
    return action, commands(cell, action, words[1] if len(words) > 1 else "all")


def settled(action, state):
    """True when an arm in ``state`` (:class:`ArmState`) has obeyed ``action``."""
    return state in _SETTLED[action]
