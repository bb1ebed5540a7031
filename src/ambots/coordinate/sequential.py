"""Sequential mode (the original project's behaviour): the first arm sends
every other arm to its park position (A7), prints its whole part, parks
itself and starts the next arm (A1); and so on down the cell's list of
arms.  Also a one-arm job with idle arms (they are parked first)."""
from ambots.protocol import MoveTo, Start

from ambots.coordinate.emit import ArmProgram, Emitter
from ambots.coordinate.steps import Step

__all__ = ["sequential_programs"]


def sequential_steps(i, arms, layers, park, idle=()):
    """The steps of the i-th arm's program: its part's layers as sliced
    (``layers``: {layer: [Segment]}) between the parking of the others
    (first arm) and its own, then the start of the next arm."""
    arm = arms[i]
    steps = []
    if i == 0:     # the first arm moves every other arm out of the way
        steps.append(Step(directives=[MoveTo(other.id, *(round(float(v), 3) for v in park[other.name]))
                                      for other in list(arms[1:]) + list(idle)]))
    for k in sorted(layers):
        steps.append(Step(layers=[layers[k][-1].end[2]], pieces=layers[k]))
    steps.append(Step(park=park[arm.name]))        # lift clear of the part, then go to the park position
    if i + 1 < len(arms):
        steps.append(Step(directives=[Start(arms[i + 1].id)]))
    return steps


def sequential_programs(arms, read, park, idle=(), mode="sequential"):
    """{arm name: ArmProgram}, ``read``: {arm name: Sliced}."""
    programs = {}
    for i, arm in enumerate(arms):
        removed, layers = read[arm.name]
        em = Emitter(arm, mode).steps(sequential_steps(i, arms, layers, park, idle))
        programs[arm.name] = ArmProgram(arm, mode, em.lines, removed, len(layers), 1, start_first=(i == 0))
    return programs
