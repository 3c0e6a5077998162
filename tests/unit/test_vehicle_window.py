"""The window a vehicle state must fall in before the control loop takes it (issue 43,
findings 2, 3 and 9; services/control/contract.py): one state out of it is refused with an
alarm naming why, and locks no real state out; a sustained, self-consistent stream outside
it is taken after ``reset_s``; a clock that answers in another time base than the states
is refused with an alarm."""

from __future__ import annotations

import pytest

from services.control.contract import StateInput, StateReading
from services.control.core.handshake import Note
from shared.bus import Received
from shared.messages import VehicleState

LIMIT = 0.15  # s: 3 ticks at 20 Hz
OFFSET = 500.0  # s: the vehicle's clock minus this host's
DELAY = 0.005  # s: from the instant a state is valid for to its arrival here
HUGE = 2**62


def state(seq: int, stamp: float, position: tuple[float, float, float] = (0.0, 0.0, 1.0),
          velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> VehicleState:
    return VehicleState(robot="r", seq=seq, stamp=stamp, position=position, velocity=velocity)


def got(msg: VehicleState, at: float) -> Received[VehicleState]:
    return Received("aesop/r/vehicle/state", msg, at)


class Vehicle:
    """A real vehicle hovering at (0, 0, 1), a state every 10 ms, on a clock ``offset``
    ahead of this host's."""

    def __init__(self, offset: float = OFFSET) -> None:
        self.seq, self.at, self.offset = 0, 0.0, offset

    @property
    def stamp(self) -> float:
        """The stamp of the newest state."""
        return self.at - DELAY + self.offset

    def fly(self, v: StateInput, seconds: float, gate: bool = True) -> StateReading:
        """Its states for ``seconds``, each offered as it arrives; what a tick sees then."""
        for _ in range(round(seconds / 0.01)):
            self.seq += 1
            self.at += 0.01
            v.offer(got(state(self.seq, self.stamp), self.at), gate=gate)
        return v.read(self.at)

    def forged(self, seq: int, ahead_s: float, **kw: tuple[float, float, float]
               ) -> Received[VehicleState]:
        """A state ``ahead_s`` past the newest real one's stamp, arriving 1 ms after it."""
        return got(state(seq, self.stamp + ahead_s, **kw), self.at + 0.001)


def view(**kw: float) -> StateInput:
    return StateInput(limit_s=LIMIT, **kw)  # type: ignore[arg-type]


def refusals(notes: tuple[Note, ...]) -> list[str]:
    return [str(n.data["refusal"]) for n in notes if n.kind == "state_refused"]


def kinds(notes: tuple[Note, ...]) -> list[str]:
    return [n.kind for n in notes]


# --------------------------------------------------------------------------- finding 2


@pytest.mark.parametrize("gate", [True, False], ids=["flying", "waiting"])
def test_one_state_with_a_huge_seq_far_ahead_locks_no_real_state_out(gate: bool) -> None:
    """Finding 2: one state with a huge seq and a far-future stamp was taken, and every
    real one after it dropped unseen as older (0 of 1,400 in 8 s)."""
    v, real = view(), Vehicle()
    real.fly(v, 1.0, gate)
    taken = v.accepted
    v.offer(real.forged(HUGE, 1e6), gate=gate)
    reading = real.fly(v, 8.0, gate)
    assert v.accepted - taken == 800 and reading.seq == real.seq and reading.fresh
    assert refusals(reading.notes) in (["seq"], ["future"]) and v.refused == 1
    assert "state_stale" not in kinds(reading.notes)


def test_a_huge_seq_is_refused_and_a_far_future_stamp_too() -> None:
    v, real = view(), Vehicle()
    real.fly(v, 0.5)
    v.offer(real.forged(HUGE, 0.0))
    assert refusals(v.read(real.at).notes) == ["seq"]
    v.offer(real.forged(real.seq + 1, 3600.0))
    reading = v.read(real.at)
    assert refusals(reading.notes) == ["future"] and reading.seq == real.seq
    assert reading.refusals == ("future",)  # each refusal, for the service's counter
    assert real.fly(v, 0.05).seq == real.seq


def test_a_state_valid_long_before_it_arrived_is_refused_as_late() -> None:
    v, real = view(), Vehicle()
    real.fly(v, 0.5)
    v.offer(real.forged(real.seq + 1, -60.0))
    assert refusals(v.read(real.at).notes) == ["late"]


def test_older_states_are_refused_with_an_alarm_not_dropped_unseen() -> None:
    v, real = view(), Vehicle()
    real.fly(v, 0.5)
    v.offer(got(state(real.seq - 3, real.stamp - 0.03), real.at + 0.001))
    reading = v.read(real.at + 0.001)
    assert refusals(reading.notes) == ["older"] and reading.seq == real.seq
    v.offer(got(state(real.seq, real.stamp), real.at + 0.002))  # the same one again
    assert v.refused == 1  # a repeat is no refusal: it refreshes nothing


def test_a_forged_first_state_is_outlived_by_the_real_ones() -> None:
    """Nothing judges the very first state (no clock answer yet): a forged one is taken,
    the real ones are refused as older than it, with an alarm, and once they have held
    together for ``reset_s`` they are taken, and the forged one leaves the clock map."""
    v, real = view(reset_s=0.5), Vehicle()
    v.offer(got(state(HUGE, OFFSET + 1e6), 0.0))
    assert v.read(0.0).seq == HUGE
    reading = real.fly(v, 0.3)
    assert reading.seq == HUGE and not reading.fresh
    assert refusals(reading.notes) == ["older"]
    reading = real.fly(v, 0.3)
    assert reading.seq == real.seq and reading.fresh and "state_reset" in kinds(reading.notes)
    assert reading.clock == "arrival" and reading.age == pytest.approx(0.0, abs=1e-9)
    assert real.fly(v, 1.0).seq == real.seq


def test_refused_states_are_taken_only_as_a_stream() -> None:
    """Two states refused alike, a second apart while the real vehicle is silent, are no
    stream that has held together: neither is taken."""
    v, real = view(reset_s=0.5), Vehicle()
    real.fly(v, 0.5)
    v.offer(real.forged(real.seq + 1, 3600.0))
    real.at += 1.0
    v.offer(real.forged(real.seq + 2, 3600.0))
    reading = v.read(real.at)
    assert reading.seq == real.seq and refusals(reading.notes) == ["future"]
    assert v.refused == 2 and "state_reset" not in kinds(reading.notes)


def test_a_steady_delay_is_no_refusal_and_the_clock_makes_up_for_it() -> None:
    """A vehicle whose states are a second old when they arrive (the closed-loop bench flies
    up to 10 s) is taken, its clock answers in use."""
    v = view()
    v.clock.sample(0.0, 0.001, OFFSET + 0.0005)
    for seq in range(1, 50):
        v.offer(got(state(seq, OFFSET + seq * 0.01 - 1.0), seq * 0.01))
    reading = v.read(0.49)
    assert reading.seq == 49 and reading.clock == "sync" and not refusals(reading.notes)
    assert reading.age == pytest.approx(1.0)


def test_a_forged_first_state_is_refused_against_the_vehicles_clock() -> None:
    """With a clock answer to judge it by, a first state far ahead of the vehicle's clock is
    refused, and the real ones are taken: the clock map is not poisoned."""
    v, real = view(), Vehicle()
    v.clock.sample(0.0, 0.001, OFFSET + 0.0005)
    v.offer(got(state(HUGE, OFFSET + 3600.0), 0.0))
    reading = real.fly(v, 0.2)
    assert refusals(reading.notes) == ["future"] and reading.seq == real.seq
    assert reading.clock == "sync" and reading.age == pytest.approx(DELAY, abs=1e-6)


def test_a_restarted_vehicle_is_still_taken_and_one_whose_clock_went_back_after_reset_s(
        ) -> None:
    v, real = view(reset_s=0.5), Vehicle()
    real.fly(v, 1.0)
    real.seq = 0  # restarted: a lower seq with a later stamp
    reading = real.fly(v, 0.5)
    assert reading.seq == real.seq and not refusals(reading.notes)
    real.seq, real.offset = 0, 3.0  # restarted on its time since boot: the clock went back
    reading = real.fly(v, 0.3)
    assert reading.seq != real.seq and refusals(reading.notes) == ["older"]
    reading = real.fly(v, 0.3)
    assert reading.seq == real.seq and "state_reset" in kinds(reading.notes)
    assert reading.fresh and reading.age == pytest.approx(0.0, abs=1e-9)


# --------------------------------------------------------------------------- finding 3


def test_a_stamp_far_ahead_does_not_widen_the_jump_check() -> None:
    """Finding 3: a state 8 m off stamped 60 s ahead was planned from (the jump check's
    reach grew as 5 t^2 / 2 with the stamps' gap)."""
    v, real = view(jump_m=0.5, max_accel=5.0), Vehicle()
    real.fly(v, 1.0)
    v.offer(real.forged(real.seq + 1, 60.0, position=(8.0, 0.0, 1.0)))
    reading = v.read(real.at + 0.001)
    assert reading.seq == real.seq and refusals(reading.notes) == ["future"]


def test_the_jump_check_reaches_as_far_as_the_time_that_passed_here() -> None:
    """Within the window a stamp 0.4 s ahead of a state that arrived 1 ms after the last
    one buys no reach: 0.85 m off is a jump (5 (0.4)^2 / 2 would have let it in)."""
    v, real = view(jump_m=0.5, max_accel=5.0), Vehicle()
    real.fly(v, 1.0)
    v.offer(real.forged(real.seq + 1, 0.4, position=(0.85, 0.0, 1.0)))
    reading = v.read(real.at + 0.001)
    assert reading.seq == real.seq and refusals(reading.notes) == ["jump"]


@pytest.mark.parametrize("first", [True, False], ids=["first state", "in flight"])
def test_an_implausible_speed_is_refused(first: bool) -> None:
    v, real = view(), Vehicle()
    if not first:
        real.fly(v, 0.5)
    v.offer(real.forged(real.seq + 1, 0.01, velocity=(1e6, 0.0, 0.0)))
    reading = v.read(real.at + 0.001)
    assert refusals(reading.notes) == ["speed"] and reading.seq == (None if first else real.seq)


# --------------------------------------------------------------------------- finding 9


@pytest.mark.parametrize("off", [1000.0, -1000.0])
def test_a_clock_in_another_time_base_is_refused_with_an_alarm(off: float) -> None:
    """Finding 9: a clock answering in another time base than the stamps made every state
    look 1,000 s old, without an alarm. Its answers are refused (said once); the states'
    arrivals map the clock instead."""
    v, real = view(), Vehicle()
    real.fly(v, 0.5)
    v.clock.sample(real.at, real.at + 0.001, real.stamp + off)
    reading = real.fly(v, 0.5)
    assert reading.clock == "arrival" and reading.age == pytest.approx(0.0, abs=1e-9)
    alarms = [n for n in reading.notes if n.kind == "clock_refused"]
    assert len(alarms) == 1 and alarms[0].severity == "alarm"
    assert reading.seq == real.seq and reading.fresh and not refusals(reading.notes)
    v.clock.sample(real.at, real.at + 0.001, real.stamp + DELAY)  # a right one again
    reading = real.fly(v, 0.05)
    assert reading.clock == "sync" and "clock_agrees" in kinds(reading.notes)


@pytest.mark.parametrize("off", [1000.0, -1000.0])
def test_a_clock_in_another_time_base_from_the_start_locks_nothing_out(off: float) -> None:
    """Before any state is taken, a clock answer is all there is to judge the first state
    by: the states it refuses are taken once they have held together for ``reset_s``, and
    the clock is refused then."""
    v, real = view(reset_s=0.5), Vehicle()
    v.clock.sample(0.0, 0.001, OFFSET + off)
    reading = real.fly(v, 0.3)
    assert reading.seq is None and refusals(reading.notes) == ["late" if off > 0 else "future"]
    reading = real.fly(v, 0.3)
    assert reading.seq == real.seq and reading.fresh and reading.clock == "arrival"
    assert {"state_reset", "clock_refused"} <= set(kinds(reading.notes))
