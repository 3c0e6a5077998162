"""The vehicle as the control loop sees it (services/control/contract.py): freshness by
arrival and seq, refusals, the clock map, delay compensation, and the set-point."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.control.contract import ClockMap, StateInput, setpoint, state_vector
from services.control.core.aesop import ControlOutput, carried_lag, carry_forward
from services.control.core.mpc import SolveStatus
from services.control.core.scenario import load_scenario, planning_model
from shared.bus import Received
from shared.frames import euler_from_quaternion, quaternion_from_euler
from shared.messages import Mode, VehicleState

LIMIT = 0.15  # s: 3 ticks at 20 Hz


def state(seq: int, stamp: float, position=(0.0, 0.0, 1.0), velocity=(0.0, 0.0, 0.0),
          **kw: object) -> VehicleState:
    return VehicleState(robot="r", seq=seq, stamp=stamp, position=position, velocity=velocity,
                        **kw)


def got(msg: VehicleState, at: float) -> Received[VehicleState]:
    return Received("aesop/r/vehicle/state", msg, at)


def view(**kw: object) -> StateInput:
    return StateInput(limit_s=LIMIT, **kw)  # type: ignore[arg-type]


def test_quaternions_and_euler_angles_round_trip() -> None:
    for angles in [(0.0, 0.0, 0.0), (0.3, -0.2, 1.0), (-0.1, 0.25, -2.5)]:
        q = quaternion_from_euler(*angles)
        assert math.isclose(sum(v * v for v in q), 1.0)
        assert euler_from_quaternion(q) == pytest.approx(angles)
    msg = state(1, 0.0, attitude=quaternion_from_euler(0.1, 0.2, 0.3), body_rates=(1, 2, 3))
    x = state_vector(msg)
    assert x[0:3].tolist() == [0.0, 0.0, 1.0] and x[9:12].tolist() == [1.0, 2.0, 3.0]
    assert x[6:9] == pytest.approx((0.1, 0.2, 0.3))


def test_fresh_is_judged_by_arrival_and_a_repeated_seq_refreshes_nothing() -> None:
    v = view()
    assert not v.read(10.0).fresh and v.read(10.0).x is None
    first = state(1, 500.0)  # the vehicle's clock is far from ours: never compared
    v.offer(got(first, 10.0))
    assert v.read(10.1).fresh and v.read(10.1).arrival_age == pytest.approx(0.1)
    v.offer(got(first, 10.2))  # the same seq again (a stuck estimator republishing)
    reading = v.read(10.2 + LIMIT)
    assert not reading.fresh and reading.seq == 1
    assert [n.kind for n in reading.notes] == ["state_stale"]
    v.offer(got(state(2, 500.4), 10.4))
    back = v.read(10.41)
    assert back.fresh and back.seq == 2 and [n.kind for n in back.notes] == ["state_fresh"]


def test_a_restarted_vehicle_counts_again_and_an_old_message_is_ignored() -> None:
    v = view()
    v.offer(got(state(100, 50.0), 1.0))
    v.offer(got(state(99, 49.9), 1.05))  # older: a late duplicate, ignored
    assert v.read(1.05).seq == 100
    v.offer(got(state(0, 50.2), 1.2))  # a lower seq with a later stamp: it restarted
    assert v.read(1.2).seq == 0 and v.read(1.2).fresh


@pytest.mark.parametrize(("bad", "kind", "words"), [
    ({"position": (math.nan, 0.0, 1.0)}, "finite", "not finite"),
    ({"velocity": (0.0, math.inf, 0.0)}, "finite", "not finite"),
    ({"frame": "odom"}, "frame", "'odom' is not the loop's 'world'"),
    ({"attitude": (2.0, 0.0, 0.0, 0.0)}, "attitude", "not a unit quaternion"),
    ({"acceleration": (0.0, math.nan, 0.0)}, "finite", "not finite"),
])
def test_a_state_that_cannot_be_right_is_refused_with_an_alarm(bad: dict, kind: str,
                                                                words: str) -> None:
    v = view()
    v.offer(got(state(1, 0.0), 0.0))
    v.offer(got(state(2, 0.01, **bad), 0.01))
    v.offer(got(state(3, 0.02, **bad), 0.02))  # the same kind again: said once
    reading = v.read(0.03)
    refused = [n for n in reading.notes if n.kind == "state_refused"]
    assert len(refused) == 1 and refused[0].severity == "alarm" and words in refused[0].message
    assert refused[0].data["refusal"] == kind and v.refused == 2
    assert reading.seq == 1 and reading.fresh  # the last good one, still young
    later = v.read(0.2)
    assert not later.fresh and "refused" in later.notes[0].message


def test_a_jump_is_refused_until_it_has_held_then_taken_as_an_estimator_reset() -> None:
    v = view(jump_m=0.5, reset_s=0.3, max_accel=5.0)
    t = 0.0
    for seq in range(10):  # flying at 1 m/s along x
        t = seq * 0.01
        v.offer(got(state(seq, t, position=(t, 0.0, 1.0), velocity=(1.0, 0.0, 0.0)), t))
    glitch = state(10, 0.1, position=(2.1, 0.0, 1.0), velocity=(1.0, 0.0, 0.0))
    v.offer(got(glitch, 0.1))  # 2 m off where it was heading: one bad sample
    assert v.read(0.1).seq == 9 and v.refused == 1
    v.offer(got(state(11, 0.11, position=(0.11, 0.0, 1.0), velocity=(1.0, 0.0, 0.0)), 0.11))
    assert v.read(0.11).seq == 11  # the glitch is over: no reset
    seq = 12
    for k in range(40):  # the estimate moves 1 m back and stays there
        t = 0.12 + k * 0.01
        v.offer(got(state(seq, t, position=(t - 1.0, 0.0, 1.0), velocity=(1.0, 0.0, 0.0)), t))
        seq += 1
        reading = v.read(t)
        if reading.seq == seq - 1:
            break
    assert any(n.kind == "state_reset" for n in reading.notes)
    assert t - 0.12 == pytest.approx(0.3, abs=0.011)  # after reset_s, not before
    assert reading.x is not None and reading.x[0] == pytest.approx(t - 1.0)


def test_a_long_gap_widens_what_counts_as_a_jump() -> None:
    v = view(jump_m=0.5, max_accel=5.0)
    v.offer(got(state(1, 0.0), 0.0))
    v.offer(got(state(2, 1.0, position=(1.5, 0.0, 1.0)), 1.0))  # 1.5 m in 1 s: possible
    assert v.read(1.0).seq == 2


def test_no_jump_is_refused_while_no_flight_is_under_way() -> None:
    v = view()
    v.offer(got(state(1, 0.0), 0.0))
    v.offer(got(state(2, 0.01, position=(5.0, 0.0, 1.0)), 0.01), gate=False)
    assert v.read(0.01).seq == 2
    v.forget()
    v.offer(got(state(3, 0.02, position=(-5.0, 0.0, 1.0)), 0.02))
    assert v.read(0.02).seq == 3 and v.newest is not None and v.newest[0] == -5.0


def test_the_clock_map_takes_the_shortest_round_trip_and_else_the_fastest_arrival() -> None:
    clock = ClockMap(sync_max_age_s=30.0)
    assert clock.offset(0.0) is None
    for stamp, arrived in [(105.03, 0.02), (105.06, 0.05), (105.09, 0.09)]:
        clock.arrival(stamp, arrived)  # offset 105 s; the first and fastest took 10 ms
    offset, source = clock.offset(0.1)  # type: ignore[misc]
    assert source == "arrival" and offset == pytest.approx(105.01)
    clock.sample(1.0, 1.004, 106.003)  # 4 ms round trip: 106.003 - 1.002
    clock.sample(2.0, 2.0006, 107.0003)  # 0.6 ms: the better one
    offset, source = clock.offset(2.1)  # type: ignore[misc]
    assert source == "sync" and offset == pytest.approx(105.0)
    assert clock.round_trip_s(2.1) == pytest.approx(0.0006)
    assert clock.offset(40.0)[1] == "arrival"  # type: ignore[index]  # old syncs expire


def test_the_age_is_the_time_since_the_state_was_valid_on_the_vehicles_clock() -> None:
    v = view()
    v.clock.sample(0.0, 0.0, 1000.0)  # the vehicle's clock is 1000 s ahead
    v.offer(got(state(1, 999.95), 0.0))  # valid 50 ms before it arrived (its delay)
    reading = v.read(0.02)
    assert reading.clock == "sync" and reading.age == pytest.approx(0.07)
    assert reading.arrival_age == pytest.approx(0.02) and reading.fresh


@pytest.mark.parametrize("name", ["hardware", "paper"])  # point mass with lag; hover model
def test_delay_compensation_carries_the_state_forward_with_the_inputs_sent(name: str) -> None:
    """A state measured ``age`` ago, carried forward under the inputs sent since, is where
    the planning model says the vehicle is now: stepping the model itself, whole steps or
    part of one."""
    scenario = load_scenario(name)
    model = planning_model(scenario)
    rng = np.random.default_rng(0)
    hover = model.linear.u_hover
    z = model.measure(np.r_[-4.0, 0.0, 1.2, np.zeros(9)], np.zeros(model.n_lag))
    path, sent = [z], []
    for _ in range(4):  # four steps sent, each with the lag states before it
        u = hover + rng.normal(0.0, 0.3, model.m)
        sent.append((u, z[model.n - model.n_lag:].copy()))
        z = model.linear.a @ z + model.linear.b @ (u - hover)
        path.append(z)

    def plant(z: np.ndarray) -> np.ndarray:  # the 12-state the vehicle reports
        return np.r_[z[0:6], np.zeros(6)] if model.n != 12 else z.copy()

    now = path[-1]
    for back in (1, 2, 4):  # whole steps old
        carried = carry_forward(model, plant(path[4 - back]), back * scenario.dt, sent)
        assert carried[0:6] == pytest.approx(now[0:6], abs=1e-9)
    for j, f in ((1, 0.3), (3, 0.8)):  # valid a fraction f into step j
        a, b = model.linear.over(f * scenario.dt)
        mid = a @ path[j] + b @ (sent[j][0] - hover)
        age = (4 - j - f) * scenario.dt
        carried = carry_forward(model, plant(mid), age, sent)
        assert carried[0:6] == pytest.approx(now[0:6], abs=1e-9)
    assert carry_forward(model, plant(now), 0.0, sent)[0:6] == pytest.approx(now[0:6])


def test_a_reported_acceleration_is_read_with_its_state() -> None:
    """A vehicle that says what acceleration it realizes (optional) has it read with the
    state; one that does not, None."""
    v = view()
    v.offer(got(state(1, 0.0, acceleration=(0.4, -0.2, 0.0)), 0.0))
    assert v.read(0.01).acceleration == pytest.approx([0.4, -0.2, 0.0])
    v.offer(got(state(2, 0.01), 0.01))
    assert v.read(0.02).acceleration is None


def test_a_measured_lag_state_is_carried_forward_in_place_of_the_predicted_one() -> None:
    """Issue 46: the vehicle realized something other than the loop predicted from the
    commands it sent (a late set-point, its own tracking). With the acceleration it reports
    at the state's instant, the state and the lag states are carried to now from that,
    not from the prediction: both land where the vehicle is."""
    scenario = load_scenario("hardware")
    model = planning_model(scenario)
    rng = np.random.default_rng(1)
    first = model.n - model.n_lag
    z = model.measure(np.r_[-4.0, 0.0, 1.2, 0.5, 0.0, 0.0, np.zeros(6)],
                      np.array([-0.9, 0.3]))  # what the vehicle really realizes
    predicted = np.array([0.4, 0.0])  # what the loop thought it realized
    path, sent = [z], []
    for _ in range(4):
        u = rng.normal(0.0, 0.3, model.m)
        sent.append((u, predicted.copy()))
        predicted = model.advance(predicted, u)
        z = model.linear.a @ z + model.linear.b @ (u - model.linear.u_hover)
        path.append(z)
    now = path[-1]
    for back, f in ((2, 0.0), (3, 0.4)):  # whole steps old; part of a step
        j = 4 - back
        a, b = model.linear.over(f * scenario.dt)
        then = a @ path[j] + b @ (sent[j][0] - model.linear.u_hover)
        x = np.r_[then[0:6], np.zeros(6)]
        age = (back - f) * scenario.dt
        realized = then[first:]
        carried = carry_forward(model, x, age, sent, lag=realized)
        assert carried[0:6] == pytest.approx(now[0:6], abs=1e-9)
        assert carried_lag(model, realized, age, sent) == pytest.approx(now[first:], abs=1e-9)
        assert carry_forward(model, x, age, sent)[0:6] != pytest.approx(now[0:6], abs=1e-3)
    assert carried_lag(model, now[first:], 0.0, sent) == pytest.approx(now[first:])


def test_the_set_point_is_on_the_vehicles_clock_and_none_when_the_branch_is_spent() -> None:
    scenario = load_scenario("hardware")
    model = planning_model(scenario)
    v = view()
    v.clock.sample(0.0, 0.0, 1000.0)
    v.offer(got(state(7, 999.99), 0.0))
    reading = v.read(0.04)  # 50 ms old on the vehicle's clock
    ref = model.rest_state((1.0, 2.0, 1.5))
    ref[3] = 0.4
    out = ControlOutput(u=np.array([0.1, -0.2, 0.3]), mode=Mode.NOMINAL,
                        status=SolveStatus.SOLVED, plan=None, active_regions=(1, 2),
                        t_anom=None, chosen=None, reference=ref,
                        ahead=np.array([[0.2, 0.0, 0.0], [0.3, 0.0, 0.0], [0.4, 0.0, 0.0]]))
    sp = setpoint(robot="r", seq=3, output=out, model=model, reading=reading, valid_s=0.15,
                  mode=Mode.NOMINAL, period_s=0.05, ahead=2)
    assert sp is not None and sp.state_seq == 7 and sp.state_stamp == 999.99
    assert sp.t == pytest.approx(1000.04) and sp.valid_until == pytest.approx(1000.19)
    assert sp.acceleration == pytest.approx((0.1, -0.2, 0.3)) and sp.thrust is None
    assert sp.position == (1.0, 2.0, 1.5) and sp.velocity == (0.4, 0.0, 0.0)
    assert sp.ahead == ((0.2, 0.0, 0.0), (0.3, 0.0, 0.0)) and sp.step_s == 0.05
    assert sp.command_at(1000.04) == pytest.approx((0.1, -0.2, 0.3))
    assert sp.command_at(1000.095) == (0.2, 0.0, 0.0)  # late: the plan where it is by then
    assert sp.command_at(1000.145) == (0.3, 0.0, 0.0)
    alone = setpoint(robot="r", seq=3, output=out, model=model, reading=reading, valid_s=0.15,
                     mode=Mode.NOMINAL, period_s=0.05)
    assert alone is not None and alone.ahead == () and alone.step_s is None
    spent = ControlOutput(**{**out.__dict__, "blind": 0})
    assert setpoint(robot="r", seq=4, output=spent, model=model, reading=reading,
                    valid_s=0.15, mode=Mode.NOMINAL, period_s=0.05) is None
    assert setpoint(robot="r", seq=4, output=out, model=model, reading=view().read(0.0),
                    valid_s=0.15, mode=Mode.NOMINAL, period_s=0.05) is None  # no state seen
