"""The one clock's decisions (ambots.clock.Lockstep), without ROS: it moves
on only when every arm has done its step and every message is delivered, it
lands on the arms' events, and it keeps the pace it is given."""
import pytest

from ambots.clock import ArmReady, HubState, Lockstep

ARMS = {"kinova": 1, "ur10": 2}


def ready(t, nxt=None, active=True, unacked=0, last_q=None, hub_q=None):
    return ArmReady(t, nxt, active, unacked, last_q, hub_q)


def settled(clock, t, **kw):
    for name in ARMS:
        clock.arm_ready(name, ready(t, **kw))
    clock.hub_ready(HubState())


def test_waits_for_every_arm_and_the_hub():
    c = Lockstep(ARMS, max_step=2.0)
    assert c.next(0.0) is None and set(c.waiting_for()) == {"kinova", "ur10", "hub"}
    c.arm_ready("kinova", ready(0.0, 5.0))
    assert c.next(0.1) is None and "ur10" in c.waiting_for()
    c.arm_ready("ur10", ready(0.0, 7.0))
    assert c.next(0.1) is None and c.waiting_for() == ["hub"]
    c.hub_ready(HubState())
    assert c.next(0.1) == pytest.approx(2.0)            # max_step before the first event (5 s)


def test_lands_exactly_on_the_next_event():
    c = Lockstep(ARMS, max_step=10.0)
    c.arm_ready("kinova", ready(0.0, 3.25))
    c.arm_ready("ur10", ready(0.0, 7.0))
    c.hub_ready(HubState())
    t = c.next(1.0)
    assert t >= 3.25 and t - 3.25 < 1e-9                  # whole ns, never before the event
    assert c.next(1.0) is None                            # nobody has done the step to t yet


def test_messages_in_flight_hold_the_clock():
    c = Lockstep(ARMS)
    settled(c, 0.0, nxt=1.0)
    c.arm_ready("kinova", ready(0.0, 1.0, unacked=1, last_q=41))
    assert c.next(1.0) is None and "kinova" in c.waiting_for()
    c.arm_ready("kinova", ready(0.0, 1.0, last_q=41))     # acknowledged: the hub has it...
    c.hub_ready(HubState(top={1: 40}))                    # ...but this state is older than that
    assert c.next(1.0) is None and "hub<-kinova" in c.waiting_for()
    c.hub_ready(HubState(top={1: 41}, fwd={2: 900}, pending=1))     # forwarded to ur10, not acked
    assert c.next(1.0) is None and "hub" in c.waiting_for()
    c.hub_ready(HubState(top={1: 41}, fwd={2: 900}, pending=0))     # acked, but ur10 said nothing since
    assert c.next(1.0) is None and "ur10<-hub" in c.waiting_for()
    c.arm_ready("ur10", ready(0.0, 1.0, hub_q=900))
    assert c.next(1.0) == pytest.approx(1.0)


def test_sequence_numbers_wrap():
    c = Lockstep(ARMS)
    settled(c, 0.0, nxt=1.0)
    c.arm_ready("kinova", ready(0.0, 1.0, last_q=2))
    c.hub_ready(HubState(top={1: 2 ** 32 - 1}))           # just before the wrap: not yet
    assert c.next(1.0) is None
    c.hub_ready(HubState(top={1: 3}))
    assert c.next(1.0) is not None


def test_speed_paces_the_clock_against_the_wall():
    c = Lockstep(ARMS, speed=4.0, max_step=100.0)
    settled(c, 0.0, nxt=50.0)
    assert c.next(10.0) is None                           # the first call only starts the wall
    assert c.next(10.5) == pytest.approx(2.0)             # 4 x 0.5 s
    settled(c, 2.0, nxt=50.0)
    assert c.next(10.51) is None                          # not more often than min_wall_step (20 ms)
    assert c.next(10.75) == pytest.approx(3.0)


def test_time_spent_waiting_for_an_arm_does_not_count_towards_the_pace():
    c = Lockstep(ARMS, speed=10.0, max_step=100.0)
    settled(c, 0.0, nxt=50.0)
    c.arm_ready("ur10", ready(-1.0, nxt=50.0))           # ur10 late: the clock waits 5 s of wall
    assert c.next(0.0) is None and c.next(5.0) is None
    c.arm_ready("ur10", ready(0.0, nxt=50.0))
    assert c.next(5.1) == pytest.approx(1.0)              # 10 x 0.1 s, not 10 x 5.1 s


def test_idle_follows_the_wall_and_max_is_as_fast_as_the_arms():
    c = Lockstep(ARMS, speed=None, max_step=2.0)
    settled(c, 0.0, active=False)
    c.next(100.0)
    assert c.next(100.01) is None                         # idle: steps of at least 20 ms wall
    assert c.next(100.5) == pytest.approx(0.5)            # nobody prints: the wall's pace
    settled(c, 0.5, nxt=None, active=True)
    assert c.next(100.5) == pytest.approx(2.5)            # printing, no event before max_step


def test_stand_in_hub_mode_waits_for_the_arms_only():
    c = Lockstep(ARMS, hub=False)
    c.arm_ready("kinova", ready(0.0, 1.0))
    c.arm_ready("ur10", ready(0.0, 1.0))
    assert c.next(0.0) == pytest.approx(1.0)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="speed"):
        Lockstep(ARMS, speed=0)
    with pytest.raises(ValueError, match="max_step"):
        Lockstep(ARMS, max_step=-1)
