"""The control loop without I/O: the deadline scheduler on a fake clock, and the runtime's
tick (fail-safe verdicts, decisions routed by request_id, the messages it builds), flying
the simulator's vehicle in process (tests/vehicles.py)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from services.control.core.regions import Region
from services.control.core.scenario import Scenario
from services.control.loop import (
    ControlRuntime,
    FixedRateScheduler,
    LoopStats,
    NotNominal,
    TickResult,
    TickTiming,
    next_index,
)
from services.control.settings import ControlSettings
from shared.bus import Received
from shared.messages import (
    AnomalyVerdict,
    DetectionMatch,
    Observation,
    PairMatch,
    ReasonerDecision,
    VehicleState,
)
from tests.vehicles import Vehicle, fly_tick

# A small geometry that solves in milliseconds (see tests/unit/test_control_mpc.py).
REGIONS = (
    Region(1, "hold", "holding zone", "hover", (0.3, -0.8, 0.8), (1.3, -0.3, 1.2)),
    Region(2, "roof", "rooftop", "landing", (0.3, 0.3, 0.0), (1.3, 0.8, 0.2)),
    Region(3, "lot", "parking lot", "landing", (-0.8, -0.5, 0.0), (-0.3, 0.5, 0.2)),
)
SCENARIO = Scenario("light", goal=(1.0, 0.0, 1.0), start_center=(0.0, 0.0, 1.0),
                    start_half_width=0.0, regions=REGIONS, horizon_s=3.0, consensus_s=0.8)
K = SCENARIO.consensus


class FakeClock:
    """Monotonic seconds that move only when someone sleeps or works."""

    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


# --------------------------------------------------------------------------- scheduler


def test_deadlines_never_drift_and_jitter_is_the_lateness() -> None:
    clock = FakeClock()
    late = 0.0007  # every wake-up oversleeps a little, as a real thread does

    def sleep(seconds: float) -> None:
        clock.sleep(seconds + late)

    scheduler = FixedRateScheduler(0.1, clock=clock, sleep=sleep, spin_s=0.0)
    start = clock.now
    timings: list[TickTiming] = []

    def tick(deadline: float) -> None:
        clock.now += 0.03  # work

    scheduler.run(tick, on_tick=timings.append, max_ticks=1000)
    assert [t.index for t in timings] == list(range(1000))
    for t in timings:  # deadline k is start + k * period, whatever the lateness before
        assert t.deadline == pytest.approx(start + t.index * 0.1, abs=1e-9)
    assert timings[-1].deadline - start == pytest.approx(99.9, abs=1e-9)
    assert all(t.jitter_s == pytest.approx(late) for t in timings[1:])
    assert timings[0].jitter_s == 0.0  # the first tick starts at once
    stats = scheduler.stats.summary()
    assert stats["ticks"] == 1000 and stats["overruns"] == 0 and stats["missed_ticks"] == 0
    assert stats["jitter_p50_ms"] == pytest.approx(0.7, abs=1e-3)
    assert stats["tick_p50_ms"] == pytest.approx(30.0, abs=1e-3)


def test_the_last_stretch_before_a_deadline_is_spun_not_slept() -> None:
    """Sleep would oversleep by as much again; the scheduler sleeps until ``spin_s`` before
    the deadline and then only reads the clock, which advances by itself here."""
    ticks = iter(range(10**6))
    now = {"t": 0.0}
    slept: list[float] = []

    def clock() -> float:
        now["t"] += 0.0001 if next(ticks) else 0.0  # each reading takes 0.1 ms
        return now["t"]

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        now["t"] += seconds

    scheduler = FixedRateScheduler(0.05, clock=clock, sleep=sleep, spin_s=0.0005)
    starts: list[float] = []
    scheduler.run(lambda deadline: starts.append(now["t"]), max_ticks=3)
    assert all(s <= 0.05 - 0.0005 + 1e-9 for s in slept)  # never slept into the last 0.5 ms
    assert starts[1] == pytest.approx(0.05, abs=2e-4) and starts[2] == pytest.approx(0.1, abs=2e-4)


def test_an_overrun_is_counted_and_skips_to_the_next_future_deadline() -> None:
    clock = FakeClock()
    scheduler = FixedRateScheduler(0.1, clock=clock, sleep=clock.sleep, spin_s=0.0)
    start = clock.now
    timings: list[TickTiming] = []

    def tick(deadline: float) -> None:
        index = round((deadline - start) / 0.1)
        clock.now += 0.35 if index == 5 else 0.01  # tick 5 runs past deadlines 6, 7 and 8

    scheduler.run(tick, on_tick=timings.append, max_ticks=10)
    indices = [t.index for t in timings]
    assert indices == [0, 1, 2, 3, 4, 5, 9, 10, 11, 12]
    five = timings[5]
    assert five.overrun and five.missed == 3
    assert not any(t.overrun for t in timings if t.index != 5)
    assert timings[6].deadline == pytest.approx(start + 0.9)
    assert timings[6].jitter_s == pytest.approx(0.0, abs=1e-9)  # it waited for tick 9
    assert scheduler.stats.overruns == 1 and scheduler.stats.missed == 3


def test_stop_ends_the_loop_from_another_thread() -> None:
    scheduler = FixedRateScheduler(0.005)
    thread = threading.Thread(target=scheduler.run, args=(lambda deadline: None,))
    thread.start()
    time.sleep(0.05)
    scheduler.stop()
    thread.join(2.0)
    assert not thread.is_alive() and scheduler.stats.ticks > 1


def test_next_index() -> None:
    assert next_index(0.0, 0.1, 4, 0.45) == (5, 0)
    assert next_index(0.0, 0.1, 4, 0.5) == (5, 0)  # ending on the next deadline is in time
    assert next_index(0.0, 0.1, 4, 0.5001) == (6, 1)
    assert next_index(0.0, 0.1, 4, 0.95) == (10, 5)


def test_stats_percentiles() -> None:
    stats = LoopStats(window=100)
    for i in range(200):  # only the newest 100 count
        jitter = 0.001 * (i - 100) if i >= 100 else 1.0
        stats.record(TickTiming(i, 0.0, jitter, jitter + 0.002, False, 0))
    summary = stats.summary()
    assert summary["ticks"] == 200
    assert summary["jitter_p50_ms"] == pytest.approx(49.5)
    assert summary["jitter_p99_ms"] == pytest.approx(98.01)
    assert summary["tick_p99_ms"] == pytest.approx(2.0)


# --------------------------------------------------------------------------- runtime


VEHICLES: dict[int, Vehicle] = {}  # each runtime's vehicle, by id(runtime)


def runtime(clock: FakeClock, start: tuple[float, float, float] = (0.0, 0.0, 1.0),
            scenario: Scenario = SCENARIO, **kw: object) -> ControlRuntime:
    settings = ControlSettings(verdict_stale_s=0.5, robot="drone1", **kw)
    rt = ControlRuntime(settings, scenario, clock=clock)
    VEHICLES[id(rt)] = Vehicle(scenario, start, clock.now)
    return rt


def verdict(clock: FakeClock, seq: int, anomaly: bool) -> Received[AnomalyVerdict]:
    message = AnomalyVerdict(robot="drone1", seq=seq, score=-0.9, threshold=-0.95,
                             is_anomaly=anomaly, k=1, model="m", cache="c", cache_version=1,
                             latency_ms=1.0)
    return Received("aesop/drone1/anomaly", message, clock.now)


async def tick(rt: ControlRuntime, clock: FakeClock, v: Received[AnomalyVerdict] | None,
               decision: ReasonerDecision | None = None,
               observation: Received[Observation] | Observation | None = None) -> TickResult:
    result = fly_tick(rt, VEHICLES[id(rt)], clock.now, verdict=v, decision=decision,
                      observation=observation)
    clock.now += 0.1
    return result


def kinds(result: TickResult) -> list[str]:
    return [e.kind for e in result.events]


async def test_the_flight_waits_for_the_detector_then_starts_without_an_alarm() -> None:
    clock = FakeClock()
    rt = runtime(clock)
    waiting = [await tick(rt, clock, None) for _ in range(3)]
    assert all(r.state.mode == "waiting" and r.request is None for r in waiting)
    assert all(r.state.t == 0.0 and r.state.x[:3] == (0.0, 0.0, 1.0) for r in waiting)
    assert kinds(waiting[0]) == ["waiting"] and not any(kinds(r) for r in waiting[1:])
    started = await tick(rt, clock, verdict(clock, 1, False))
    assert started.state.mode == "nominal" and started.state.t == 0.0
    assert "flight_started" in kinds(started) and "verdict_stale" not in kinds(started)
    moved = await tick(rt, clock, verdict(clock, 2, False))
    assert moved.state.t == pytest.approx(SCENARIO.dt)


async def started(clock: FakeClock, **kw: object) -> ControlRuntime:
    rt = runtime(clock, **kw)
    await tick(rt, clock, verdict(clock, 0, False))
    return rt


async def test_silence_is_an_anomaly_the_reasoner_cannot_continue_out_of() -> None:
    """Stale verdicts: one alarm and one request per silent spell, the reasoner told the
    detector is silent and not offered "continue"; a "continue" is refused; with no region
    by K the fallback is committed as for any anomaly."""
    clock = FakeClock()
    rt = await started(clock)
    old = verdict(clock, 0, False)
    clock.now += 0.6  # the detector stops answering
    silent = await tick(rt, clock, old)
    assert silent.stale and silent.anomaly and silent.state.mode == "anomaly_pending"
    alarm = [e for e in silent.events if e.kind == "verdict_stale"]
    assert len(alarm) == 1 and alarm[0].severity == "alarm" and "silent" in alarm[0].message
    request = silent.request
    assert request is not None and "gone silent" in request.observation.text
    assert 0 not in [o.index for o in request.options]
    cont = ReasonerDecision(request_id=request.request_id, choice=0, source="llm",
                            latency_ms=1.0)
    refused = await tick(rt, clock, old, cont)
    assert refused.state.mode == "anomaly_pending" and "continue_refused" in kinds(refused)
    # the decision slot keeps its newest answer: every tick sees the same "continue" again
    later = [await tick(rt, clock, old, cont) for _ in range(K - 2)]
    assert not any(r.request for r in later) and not any("verdict_stale" in kinds(r)
                                                         for r in later)
    assert not any("continue_refused" in kinds(r) for r in later)  # said once, not per tick
    assert all(r.state.mode == "anomaly_pending" for r in later)
    committed = await tick(rt, clock, old, cont)
    assert committed.state.mode == "recovering" and committed.output.fallback
    assert committed.state.chosen in [o.index for o in request.options]


async def test_a_camera_that_restarts_its_count_is_not_silent() -> None:
    """Observation numbers that start again from 1 (the camera or its driver restarted)
    are new observations: their verdicts are fresh."""
    clock = FakeClock()
    rt = runtime(clock)
    for seq in range(1, 40):
        seen = Received("aesop/drone1/observation",
                        Observation(robot="drone1", seq=seq, text="a red box"), clock.now)
        result = await tick(rt, clock, verdict(clock, seq, False), observation=seen)
    assert result.state.mode == "nominal" and not result.stale
    for seq in range(1, 8):  # the count starts again
        seen = Received("aesop/drone1/observation",
                        Observation(robot="drone1", seq=seq, text="a red box"), clock.now)
        result = await tick(rt, clock, verdict(clock, seq, False), observation=seen)
        assert not result.stale, seq
    assert result.state.mode == "nominal"


async def test_a_region_answer_to_the_silence_is_taken() -> None:
    clock = FakeClock()
    rt = await started(clock)
    old = verdict(clock, 0, False)
    clock.now += 0.6
    request = (await tick(rt, clock, old)).request
    region = request.options[0].index
    chosen = ReasonerDecision(request_id=request.request_id, choice=region, source="llm",
                              latency_ms=1.0)
    taken = await tick(rt, clock, old, chosen)
    assert taken.state.mode == "recovering" and taken.state.chosen == region


async def test_fresh_verdicts_end_the_silent_spells_episode() -> None:
    clock = FakeClock()
    rt = await started(clock)
    old = verdict(clock, 0, False)
    clock.now += 0.6
    assert (await tick(rt, clock, old)).state.mode == "anomaly_pending"
    back = await tick(rt, clock, verdict(clock, 1, False))
    assert back.state.mode == "nominal" and not back.stale
    assert {"verdict_fresh", "silence_ended"} <= set(kinds(back))
    last = verdict(clock, 2, False)
    await tick(rt, clock, last)
    clock.now += 0.6  # a new silent spell: a new alarm, a new request
    again = await tick(rt, clock, last)
    assert again.request is not None and "verdict_stale" in kinds(again)


async def test_fresh_verdicts_flagging_the_scene_turn_the_silence_into_an_anomaly() -> None:
    clock = FakeClock()
    rt = await started(clock)
    old = verdict(clock, 0, False)
    clock.now += 0.6
    silent = await tick(rt, clock, old)
    flagged = await tick(rt, clock, verdict(clock, 1, True))
    assert "silence_ended" in kinds(flagged) and flagged.request is not None
    assert flagged.request.request_id != silent.request.request_id
    assert flagged.request.options[0].index == 0  # continue is an option again


async def test_a_backlog_of_verdicts_on_old_observations_is_not_fresh() -> None:
    """A verdict is as old as the observation it answers, however recently it arrived."""
    clock = FakeClock()
    rt = runtime(clock)
    scene = "a red box on the ground"
    for seq in range(3):
        obs = Received("aesop/drone1/observation",
                       Observation(robot="drone1", seq=seq, text=scene), clock.now)
        result = await tick(rt, clock, verdict(clock, seq, False), observation=obs)
    assert result.state.mode == "nominal" and not result.stale
    backlog = []
    for seq in range(3, 12):  # observations go on; the verdicts that arrive are for seq 2
        obs = Received("aesop/drone1/observation",
                       Observation(robot="drone1", seq=seq, text=scene), clock.now)
        backlog.append(await tick(rt, clock, verdict(clock, 2, False), observation=obs))
    assert not backlog[0].stale  # 0.1 s old
    assert backlog[-1].stale and any("verdict_stale" in kinds(r) for r in backlog)
    late = await tick(rt, clock, verdict(clock, 11, False),
                      observation=Received("aesop/drone1/observation",
                                           Observation(robot="drone1", seq=12, text=scene),
                                           clock.now))
    assert not late.stale  # a verdict on a recent observation


async def test_an_anomaly_asks_the_reasoner_and_the_decision_is_routed_by_request_id() -> None:
    clock = FakeClock()
    rt = runtime(clock)
    for seq in range(3):
        result = await tick(rt, clock, verdict(clock, seq, False))
        assert result.state.mode == "nominal" and result.request is None
    scene = Observation(robot="drone1", seq=3, text="a quadrotor on the red box")
    asked = await tick(rt, clock, verdict(clock, 3, True), observation=scene)
    request = asked.request
    assert request is not None and asked.state.mode == "anomaly_pending"
    assert request.robot == "drone1" and request.observation == scene
    assert [o.index for o in request.options] == [0, *asked.output.request]
    assert request.options[0].label == "continue"
    labels = {r.index: r.label for r in REGIONS}
    assert all(o.label == labels[o.index] for o in request.options[1:])
    # due by the tick at k = K, K periods after this one, less the margin for the way back
    assert request.deadline_s == pytest.approx(K * 0.1 - 0.02)
    change = [e for e in asked.events if e.kind == "mode_change"]
    assert change and change[0].data["to"] == "anomaly_pending"
    assert change[0].data["request_id"] == request.request_id

    choice = request.options[1].index
    other = ReasonerDecision(robot="drone1", request_id="someone-else", choice=choice,
                             source="llm", latency_ms=5.0)
    ignored = await tick(rt, clock, verdict(clock, 4, True), other)
    assert ignored.state.mode == "anomaly_pending" and rt.pending == request.request_id
    mine = other.model_copy(update={"request_id": request.request_id})
    taken = await tick(rt, clock, verdict(clock, 5, True), mine)
    assert taken.state.mode == "recovering" and taken.state.chosen == choice
    event = next(e for e in taken.events if e.kind == "mode_change")
    assert event.data["to"] == "recovering" and event.data["chosen"] == choice
    assert not event.data["fallback"] and rt.pending is None
    again = await tick(rt, clock, verdict(clock, 6, True), mine)  # a duplicate changes nothing
    assert again.state.mode == "recovering"
    assert not [e for e in again.events if "decision" in e.message]


NAMED = (DetectionMatch(detection="a quadrotor on the red box",
                        nearest="a quadrotor on the ground", similarity=0.83, p_value=0.01),)
PAIR = PairMatch(detections=("a person on the floor", "a quadrotor on the ground"),
                 nearest=("a person on the floor", "a red box"), similarity=0.4, p_value=0.01)


@pytest.mark.parametrize(("named", "pair"), [(NAMED, None), ((), PAIR), (NAMED, PAIR)])
async def test_the_request_carries_what_the_verdict_named(
        named: tuple[DetectionMatch, ...], pair: PairMatch | None) -> None:
    clock = FakeClock()
    rt = await started(clock)
    flagged = verdict(clock, 1, True)
    flagged = Received(flagged.key, flagged.message.model_copy(
        update={"detections": named, "pair": pair}), flagged.received_at)
    scene = Observation(robot="drone1", seq=1, text="a quadrotor on the red box")
    asked = await tick(rt, clock, flagged, observation=scene)
    assert asked.request is not None
    assert asked.request.unusual == named and asked.request.unusual_pair == pair


async def test_continue_goes_back_to_nominal_and_only_a_new_verdict_asks_again() -> None:
    clock = FakeClock()
    rt = runtime(clock)
    await tick(rt, clock, verdict(clock, 0, False))
    flagged = verdict(clock, 1, True)
    asked = await tick(rt, clock, flagged)
    assert asked.request is not None
    cont = ReasonerDecision(request_id=asked.request.request_id, choice=0, source="llm",
                            latency_ms=1.0)
    back = await tick(rt, clock, flagged, cont)
    assert back.state.mode == "nominal" and back.request is None
    assert (await tick(rt, clock, flagged)).request is None  # the answered verdict
    assert (await tick(rt, clock, verdict(clock, 2, True))).request is not None


async def test_no_decision_by_k_commits_the_fallback_with_an_alarm() -> None:
    clock = FakeClock()
    rt = runtime(clock)
    await tick(rt, clock, verdict(clock, 0, False))
    asked = await tick(rt, clock, verdict(clock, 1, True))
    assert asked.request is not None
    results = [await tick(rt, clock, verdict(clock, 2 + i, True)) for i in range(K)]
    assert [r.state.mode for r in results[:-1]] == ["anomaly_pending"] * (K - 1)
    last = results[-1]
    assert last.state.mode == "recovering" and last.output.fallback
    alarm = [e for e in last.events if e.kind == "fallback"]
    assert len(alarm) == 1 and alarm[0].severity == "alarm" and "no decision by K" in \
        alarm[0].message
    assert last.state.t_anom == pytest.approx(asked.state.t)


async def test_messages_carry_the_state_the_input_and_the_plan_tree() -> None:
    clock = FakeClock()
    rt = runtime(clock)
    results = [await tick(rt, clock, verdict(clock, i, False)) for i in range(3)]
    for i, r in enumerate(results):
        assert r.state.robot == "drone1" and r.state.t == pytest.approx(i * SCENARIO.dt)
        assert len(r.state.x) == 12 and len(r.state.u) == 4
    assert results[0].state.x[:3] == (0.0, 0.0, 1.0)
    assert results[1].state.x != results[0].state.x  # the plant moved
    plan = results[-1].plan
    assert plan is not None and plan.robot == "drone1" and plan.status == "solved"
    assert len(plan.nominal) == SCENARIO.horizon + 1 and len(plan.nominal[0]) == 3
    assert set(plan.recovery) == set(results[-1].state.active_regions)
    assert plan.consensus_steps == K and plan.solve_ms > 0
    assert plan.nominal[0] == pytest.approx(results[-1].state.x[:3], abs=1e-3)


async def test_regions_change_only_in_nominal_mode_and_a_bad_set_changes_nothing() -> None:
    clock = FakeClock()
    rt = runtime(clock)
    await tick(rt, clock, verdict(clock, 0, False))
    far = (Region(1, "far", "holding zone", "hover", (0.0, 0.0, 1.0), (1.0, 9.5, 2.0)),)
    with pytest.raises(ValueError, match=r"regions\[0\]"):  # beyond the position limits
        await rt.replace_regions(far)
    assert rt.scenario.regions == REGIONS
    await rt.replace_regions(REGIONS[:2])
    assert rt.scenario.regions == REGIONS[:2]
    result = await tick(rt, clock, verdict(clock, 1, True))
    assert "regions_updated" in kinds(result) and result.request is not None
    assert set(result.output.request) <= {1, 2}
    with pytest.raises(NotNominal):
        await rt.replace_regions(REGIONS)
    assert rt.scenario.regions == REGIONS[:2]


async def test_new_regions_mid_flight_keep_the_flights_progress() -> None:
    """A region change swaps the controller, not the flight: the route stays where it was
    (past the approach waypoint, it does not climb back to it) and so do the lag states
    of the commands already sent."""
    from dataclasses import replace

    scene = replace(SCENARIO, model="point-mass", approach_height=0.3,
                    acceleration_lag=(0.08, 0.08, 0.0))
    clock = FakeClock()
    rt = runtime(clock, (1.0, 0.0, 1.3), scene)
    await tick(rt, clock, None)  # waiting: the vehicle seen away from the scene's start ...
    await rt.reset()  # ... where the controller is warmed up now
    for seq in range(8):  # at rest on the waypoint: the route moves on to the descent
        await tick(rt, clock, verdict(clock, seq, False))
    assert rt.controller.route.index == 1
    lag = rt.controller.lag.copy()
    assert np.any(lag != 0.0)  # the descent has been commanded
    await rt.replace_regions(REGIONS[:2])
    assert rt.controller.route.index == 1
    assert np.array_equal(rt.controller.lag, lag)


async def test_reset_restarts_the_flight_from_wherever_the_vehicle_is() -> None:
    clock = FakeClock()
    rt = await started(clock)
    old = verdict(clock, 0, False)
    clock.now += 0.6
    await tick(rt, clock, old)  # silent: asks the reasoner, mode pending
    assert rt.mode.value == "anomaly_pending"
    VEHICLES[id(rt)].teleport((0.5, 0.0, 1.0), clock.now)  # moved between flights
    await tick(rt, clock, old)
    position = await rt.reset()
    assert position is not None and np.allclose(position, (0.5, 0.0, 1.0), atol=1e-6)
    assert rt.mode.value == "waiting"
    held = await tick(rt, clock, old)  # the old verdict does not start the new flight
    assert held.state.mode == "waiting" and "reset" in kinds(held)
    assert "verdict_stale" not in kinds(held) and not held.setpoint  # nothing sent
    result = await tick(rt, clock, verdict(clock, 1, False))
    assert result.state.t == 0.0 and result.state.x[:3] == pytest.approx((0.5, 0.0, 1.0), abs=0.01)
    assert result.state.mode == "nominal" and "flight_started" in kinds(result)
    assert result.setpoint is not None


async def test_a_scene_the_reasoner_cleared_does_not_ask_again_until_a_reset() -> None:
    clock = FakeClock()
    rt = runtime(clock)
    keyboard = "a keyboard on the ground"
    seen = [Observation(robot="drone1", seq=seq, text=keyboard) for seq in range(6)]
    await tick(rt, clock, verdict(clock, 0, False), observation=seen[0])
    asked = await tick(rt, clock, verdict(clock, 1, True), observation=seen[1])
    assert asked.request is not None and asked.request.observation.text == keyboard
    cont = ReasonerDecision(request_id=asked.request.request_id, choice=0, source="llm",
                            latency_ms=1.0)
    back = await tick(rt, clock, verdict(clock, 2, True), cont, observation=seen[2])
    assert back.state.mode == "nominal" and back.request is None
    assert "anomaly_cleared" in kinds(back) and not back.anomaly
    for seq in (3, 4):  # still in view: flagged, not asked, said once
        later = await tick(rt, clock, verdict(clock, seq, True), observation=seen[seq])
        assert later.request is None and not later.anomaly
        assert "anomaly_cleared" not in kinds(later)
    hazard = Observation(robot="drone1", seq=5, text="a quadrotor on the red box")
    other = await tick(rt, clock, verdict(clock, 5, True), observation=hazard)
    assert other.request is not None and other.request.observation == hazard

    rt2 = runtime(clock)
    await tick(rt2, clock, verdict(clock, 10, False), observation=seen[0])
    first = await tick(rt2, clock, verdict(clock, 11, True),
                       observation=seen[1].model_copy(update={"seq": 11}))
    cont = cont.model_copy(update={"request_id": first.request.request_id})
    await tick(rt2, clock, verdict(clock, 12, True), cont,
               observation=seen[1].model_copy(update={"seq": 12}))
    await rt2.reset()
    again = await tick(rt2, clock, verdict(clock, 13, True),
                       observation=seen[1].model_copy(update={"seq": 13}))
    assert again.request is not None  # a new flight judges the scene afresh


async def test_a_cleared_scene_is_its_text_and_its_detections() -> None:
    """Issue 26, finding 7: cleared scenes were keyed by the text alone, so a scene the
    reasoner let pass also cleared the same words with other detections behind them."""
    from shared.messages import Detection

    clock = FakeClock()
    rt = runtime(clock)
    text = "the landing pad"
    clear = (Detection(label="a drill", where="on the ground"),)
    person = (Detection(label="a person", where="on the pad"),)
    await tick(rt, clock, verdict(clock, 0, False),
               observation=Observation(robot="drone1", seq=0, text=text, detections=clear))
    asked = await tick(rt, clock, verdict(clock, 1, True), observation=Observation(
        robot="drone1", seq=1, text=text, detections=clear))
    assert asked.request is not None
    cont = ReasonerDecision(request_id=asked.request.request_id, choice=0, source="llm",
                            latency_ms=1.0)
    back = await tick(rt, clock, verdict(clock, 2, True), cont, observation=Observation(
        robot="drone1", seq=2, text=text, detections=clear))
    assert "anomaly_cleared" in kinds(back)
    same_words = await tick(rt, clock, verdict(clock, 3, True), observation=Observation(
        robot="drone1", seq=3, text=text, detections=person))
    assert same_words.request is not None  # other detections: another scene, asked about


async def test_a_non_finite_state_is_refused_with_an_alarm_and_the_loop_goes_on() -> None:
    clock = FakeClock()
    rt = await started(clock)
    before = await tick(rt, clock, verdict(clock, 1, False))
    vehicle = VEHICLES[id(rt)]
    good = vehicle.advance(clock.now)
    assert good is not None
    bad = good.message.model_copy(update={"seq": good.message.seq + 1,
                                          "position": (float("nan"), 0.0, 1.0)})
    result = rt.tick(deadline=clock.now, verdict=verdict(clock, 2, False),
                     state=Received(good.key, bad, clock.now))
    vehicle.follow(result, clock.now)
    clock.now += 0.1
    alarm = [e for e in result.events if e.kind == "state_refused"]
    assert alarm and alarm[0].severity == "alarm" and "not finite" in alarm[0].message
    assert result.state.mode == "nominal" and result.state.encode()
    assert all(np.isfinite(result.state.x))  # never a NaN on the bus
    after = await tick(rt, clock, verdict(clock, 3, False))
    assert not [e for e in after.events if e.kind == "state_refused"]
    assert after.state.x != before.state.x and after.plan is not None


async def test_a_vehicle_away_from_the_warm_up_point_starts_once_warmed_up_there() -> None:
    """Waiting, the loop sees the vehicle far from where its controller was warmed up: it
    builds one warmed up there off the tick and starts only once it is swapped in, never
    with a cold solve."""
    clock = FakeClock()
    rt = runtime(clock, (0.6, 0.0, 1.0))
    first = await tick(rt, clock, verdict(clock, 1, False))
    assert first.state.mode == "waiting"  # fresh verdict, fresh state: still warming up
    for seq in range(2, 400):
        result = await tick(rt, clock, verdict(clock, seq, False))
        if result.state.mode != "waiting":
            break
        time.sleep(0.01)  # the build runs on its own thread, in real time
    assert result.state.mode == "nominal" and "flight_started" in kinds(result)
    assert np.allclose(rt._warm_at, (0.6, 0.0, 1.0), atol=0.05)
    rt.close()


async def test_the_flight_waits_for_a_fresh_vehicle_state_too() -> None:
    clock = FakeClock()
    settings = ControlSettings(verdict_stale_s=0.5, robot="drone1")
    rt = ControlRuntime(settings, SCENARIO, clock=clock)
    held = rt.tick(deadline=clock.now, verdict=verdict(clock, 1, False))  # no vehicle yet
    assert held.state.mode == "waiting" and held.setpoint is None
    vehicle = Vehicle(SCENARIO, (0.0, 0.0, 1.0), clock.now)
    clock.now += 0.1
    flying = fly_tick(rt, vehicle, clock.now, verdict=verdict(clock, 2, False))
    assert flying.state.mode == "nominal" and flying.setpoint is not None
    assert flying.setpoint.thrust is not None and flying.setpoint.acceleration is None
    assert isinstance(vehicle.slot.message, VehicleState)
