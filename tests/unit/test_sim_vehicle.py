"""The simulated vehicle (services/sim/vehicle.py): how it reports its state, follows
set-points and holds itself when they stop, and the faults it can be given."""

from __future__ import annotations

import numpy as np
import pytest

from services.control.core.scenario import load_scenario
from services.sim.vehicle import HOLD_EASE_S, Reporting, SimVehicle
from shared.frames import euler_from_quaternion
from shared.messages import Mode, VehicleSetpoint

HARDWARE = load_scenario("hardware")
PAPER = load_scenario("paper")
START = np.r_[-4.0, 0.0, 1.2, np.zeros(9)]


def vehicle(reporting: Reporting | None = None, scenario=HARDWARE, **kw) -> SimVehicle:
    return SimVehicle(scenario, START, reporting or Reporting(), now=100.0, **kw)


def accel(seq: int, t: float, a=(0.5, 0.0, 0.0), valid_s: float = 0.15) -> VehicleSetpoint:
    return VehicleSetpoint(seq=seq, state_seq=0, state_stamp=t, t=t, valid_until=t + valid_s,
                           mode=Mode.NOMINAL, acceleration=a, position=(0.0, 0.0, 0.0),
                           velocity=(0.0, 0.0, 0.0))


def test_states_come_at_the_rate_each_published_after_the_delay() -> None:
    v = vehicle(Reporting(rate_hz=50.0, delay_s=0.03))
    reports = v.advance(101.0)
    stamps = [r.state.stamp for r in reports]
    assert len(reports) == 49  # valid at 100.00 .. 100.96, each out 30 ms later
    assert np.diff(stamps) == pytest.approx(0.02) and stamps[0] == pytest.approx(100.0)
    assert all(r.at == pytest.approx(r.state.stamp + 0.03) for r in reports)
    assert np.all(np.diff([r.state.seq for r in reports]) == 1)
    first = reports[0].state
    assert first.position == pytest.approx((-4.0, 0.0, 1.2)) and first.frame == "world"
    assert euler_from_quaternion(first.attitude) == pytest.approx((0.0, 0.0, 0.0))


def test_noise_drops_and_a_clock_offset() -> None:
    v = vehicle(Reporting(position_noise_m=0.01, drop_rate=0.5, clock_offset_s=-7.0), seed=1)
    reports = v.advance(102.0)
    assert 60 < len(reports) < 140  # about half of the 200 states
    seqs = [r.state.seq for r in reports]
    assert max(np.diff(seqs)) > 1  # the lost ones leave gaps in the count
    assert reports[0].state.stamp == pytest.approx(93.0)  # its clock, 7 s behind
    spread = np.std([r.state.position[0] for r in reports])
    assert 0.005 < spread < 0.02


def test_it_follows_a_set_point_then_holds_itself_when_it_expires() -> None:
    v = vehicle()
    v.advance(100.5)
    assert v.holding  # no set-point yet: it holds where it is
    assert np.linalg.norm(v.truth[0:3] - START[0:3]) < 1e-3
    assert v.receive(accel(1, v.clock(100.5)), 100.5)
    assert not v.holding
    v.advance(100.6)  # within valid_until: accelerating along x
    moving = v.truth[3]
    assert moving > 0.01
    v.advance(101.5)  # 150 ms after its instant, no newer one: hold, brake to rest
    assert v.holding
    v.advance(106.0)
    assert np.linalg.norm(v.truth[3:6]) < 0.02 and abs(v.truth[0] - START[0]) < 0.2


def test_its_hold_eases_in_from_the_last_command_instead_of_stepping() -> None:
    """Issue 46: a hold that steps the acceleration command from the plan's to its own turns,
    in a tracking controller without clamps, into body rates past the scene's limits. The
    acceleration it flies when a set-point expires starts at the last command and reaches
    its own hold's over ``HOLD_EASE_S``, never jumping."""
    v = vehicle()
    assert v.receive(accel(1, v.clock(100.0), a=(0.8, 0.0, 0.0), valid_s=0.3), 100.0)
    applied = []
    for t in np.arange(100.01, 101.0, 0.01):
        v.advance(float(t))
        applied.append((float(t), v.applied.copy()))
    expired = [(t, u) for t, u in applied if t > 100.3 + 1e-9]
    assert v.holding and expired[0][1][0] == pytest.approx(0.8, abs=0.1)  # the last command
    steps = np.abs(np.diff([u for _, u in applied], axis=0)).max()
    assert steps < 0.2  # per 10 ms: eased, not stepped (the hold's own brakes at ~-1 m/s^2)
    later = [u for t, u in expired if t > 100.3 + HOLD_EASE_S + 0.02]
    assert later[0][0] < 0.0  # by then its own hold brakes


def test_it_flies_the_commands_ahead_each_from_its_own_instant() -> None:
    """A set-point carrying the plan's next commands 50 ms apart flies exactly as the same
    commands sent one by one on time would, even when it arrives 20 ms after its instant
    (the next command still starts at its own instant, not 50 ms after the arrival); past
    ``valid_until`` the vehicle holds."""
    def sp(seq: int, t: float, a: float, ahead=()) -> VehicleSetpoint:
        return VehicleSetpoint(seq=seq, state_seq=0, state_stamp=t, t=t, valid_until=100.15,
                               mode=Mode.NOMINAL, acceleration=(a, 0.0, 0.0),
                               position=(0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0),
                               ahead=ahead, step_s=0.05 if ahead else None)
    for arrival in (100.0, 100.02):
        packet, one_by_one, held = vehicle(), vehicle(), vehicle()
        for v in (packet, one_by_one, held):
            v.advance(arrival)
        held.receive(sp(1, 100.0, 1.0), arrival)  # the first command alone, held
        assert packet.receive(sp(1, 100.0, 1.0, ((-1.0, 0.0, 0.0), (0.5, 0.0, 0.0))), arrival)
        one_by_one.receive(sp(1, 100.0, 1.0), arrival)
        for at, a in ((100.05, -1.0), (100.1, 0.5)):
            packet.advance(at)
            one_by_one.receive(sp(2 if a < 0 else 3, at, a), at)
            assert packet.truth == pytest.approx(one_by_one.truth, abs=1e-9)
        packet.advance(100.14)
        one_by_one.advance(100.14)
        assert packet.truth == pytest.approx(one_by_one.truth, abs=1e-9)
        assert not packet.holding
        held.advance(100.14)
        assert abs(held.truth[3] - packet.truth[3]) > 0.01  # what a stretched command gives
        packet.advance(100.2)
        assert packet.holding  # past valid_until


def test_a_set_point_of_the_wrong_kind_or_an_older_one_is_not_taken() -> None:
    v = vehicle()
    motors = VehicleSetpoint(seq=1, state_seq=0, state_stamp=100.0, t=100.0,
                             valid_until=100.2, mode=Mode.NOMINAL, thrust=9.8,
                             torque=(0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0),
                             velocity=(0.0, 0.0, 0.0))
    assert not v.receive(motors, 100.0)  # the hardware scene's vehicle takes accelerations
    assert v.receive(accel(5, 100.0), 100.0)
    assert not v.receive(accel(4, 99.9), 100.01)  # older than the one it follows
    assert v.ages.refused == 2 and v.ages.received == 1
    hover = vehicle(scenario=PAPER)
    assert hover.receive(motors, 100.0)  # the paper scene's vehicle takes thrust and torques


def test_a_set_point_from_the_far_future_is_refused_and_locks_nothing_out() -> None:
    """Issue 43, finding 1: the vehicle took any set-point whose seq or t was higher, with
    no bound: one forged with seq 2^62 and t = now + 1e6 was flown, and every real one after
    it refused as older (13,677 in 25 min). A set-point for an instant more than
    ``MAX_AHEAD_S`` past the vehicle's clock, or valid for longer than ``MAX_VALID_S``, is
    refused and counted by reason; the loop's next set-points are taken."""
    v = vehicle()
    assert v.receive(accel(7, 100.0), 100.0)
    assert not v.receive(accel(2**62, 100.0 + 1e6), 100.01)  # the forged one
    assert not v.receive(accel(2**62, 100.02, valid_s=1e6), 100.02)  # valid for ever
    assert v.receive(accel(8, 100.05), 100.05)  # the real loop's next: taken
    assert v.setpoint is not None and v.setpoint.seq == 8
    assert v.ages.refusals == {"future": 1, "validity": 1} and v.ages.refused == 2
    assert v.ages.summary()["refused"] == 2


def test_after_a_reset_a_set_point_for_an_instant_before_it_is_refused() -> None:
    """Issue 46: a set-point the loop sent before a reset, delivered after it (a busy hub
    delays one by hundreds of ms), belongs to the flight before: its reference is where the
    vehicle was. The test airframe took one 0.15 s after being moved 4.2 m and flew at
    8 rad/s. A set-point for an instant before the reset is refused ("before_reset"); the
    next flight's are taken."""
    v = vehicle()
    assert v.receive(accel(7, 100.0), 100.0)
    v.reset(START, 100.2)
    assert not v.receive(accel(8, 100.1, valid_s=0.5), 100.25)  # planned before the reset
    assert v.holding and v.ages.refusals == {"before_reset": 1}
    assert v.receive(accel(9, 100.3), 100.3)  # the new flight's first: taken
    assert not v.holding


def test_after_a_reset_a_set_point_planned_from_a_state_before_it_is_refused() -> None:
    """Issue 46: a loop that lost its vehicle (a vehicle restarted, or another process
    started in its place) flies blind on the last state it had and goes on sending
    set-points, each for an instant of now. The test airframe, started anew, took one
    46 ms after it began: planned from a state 4.4 s before, its reference 2.4 m from where
    the airframe stood. A set-point planned from a state before the reset (``state_stamp``)
    is refused ("before_reset") whatever its ``t``; one planned from a state after it is
    taken."""
    v = vehicle()
    v.reset(START, 100.2)
    stale = VehicleSetpoint(seq=8, state_seq=0, state_stamp=95.9, t=100.3,
                            valid_until=100.8, mode=Mode.NOMINAL, acceleration=(0.5, 0.0, 0.0),
                            position=(-1.98, 0.8, 0.2), velocity=(0.0, 0.0, 0.0))
    assert not v.receive(stale, 100.3)
    assert v.holding and v.ages.refusals == {"before_reset": 1}
    assert v.receive(accel(9, 100.35), 100.35)  # planned from a state of this flight
    assert not v.holding


def test_faults_a_drop_out_a_stop_lost_set_points_and_a_jump() -> None:
    v = vehicle()
    v.faults.silent_until = 100.5
    assert v.advance(100.49) == [] and len(v.advance(101.0)) == 51  # 100.50 .. 101.00
    v.faults.deaf_until = 101.2
    assert not v.receive(accel(1, 101.1), 101.1) and v.holding
    assert v.receive(accel(2, 101.25), 101.25)
    v.faults.jump, v.faults.jump_until = (2.0, 0.0, 0.0), 101.4
    jumped = v.advance(101.5)
    offsets = [r.state.position[0] - v.truth[0] for r in jumped]
    assert max(offsets) > 1.5 and min(offsets) < 0.5  # only those valid before 101.4
    v.faults.stopped = True
    assert v.advance(103.0) == []


def test_the_truth_runs_time_scale_seconds_per_second() -> None:
    fast = vehicle(time_scale=2.0)
    slow = vehicle()
    for v in (fast, slow):
        v.receive(accel(1, 100.0, valid_s=10.0), 100.0)
    fast.advance(100.5)
    slow.advance(101.0)
    assert fast.truth[0:6] == pytest.approx(slow.truth[0:6], abs=1e-3)


@pytest.mark.parametrize("scenario", [HARDWARE, PAPER], ids=["hardware", "paper"])
def test_its_own_hold_brings_either_airframe_to_rest(scenario) -> None:
    """Moving at 0.5 m/s when the set-points stop: it comes to rest near where it was, the
    fast-tilting airframe briskly, the paper's slow one gently (brisk gains diverge it)."""
    x0 = np.r_[scenario.start_center, np.zeros(9)]
    v = SimVehicle(scenario, x0, Reporting(), now=0.0)  # no set-point: holding at x0
    v.plant._x[3] = 0.5
    worst = 0.0
    for t in np.arange(0.1, 20.0, 0.1):
        v.advance(float(t))
        worst = max(worst, float(np.linalg.norm(v.truth[0:3] - x0[0:3])))
    assert v.holding and worst < 0.5
    assert np.linalg.norm(v.truth[0:3] - x0[0:3]) < 0.02 and np.linalg.norm(v.truth[3:6]) < 0.01


@pytest.mark.timeout(20)
def test_commands_ahead_on_an_epoch_clock_never_stall_the_integration() -> None:
    """At epoch seconds a float's step is about 0.2 us: an instant ahead can round onto the
    vehicle's time (a first version of this code hung the simulator there); it must step on."""
    now = 1_795_689_442.4108565
    v = SimVehicle(HARDWARE, START, Reporting(clock_offset_s=0.3), now=now)
    ahead = tuple((0.1 * j, 0.0, 0.0) for j in range(8))
    sp = VehicleSetpoint(seq=1, state_seq=0, state_stamp=v.clock(now) - 1e-7,
                         t=v.clock(now) - 1e-7,
                         valid_until=v.clock(now) + 0.2, mode=Mode.NOMINAL,
                         acceleration=(0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0),
                         velocity=(0.0, 0.0, 0.0), ahead=ahead, step_s=0.02)
    assert v.receive(sp, now)
    for i in range(1, 500):
        v.advance(now + i * 0.0005 + (i % 3) * 1e-7)
    assert v.holding and np.all(np.isfinite(v.truth))
    assert sp.command_at(sp.t + 0.02) == ahead[0] and sp.switches_after(sp.t + 0.02) > sp.t + 0.02
