"""shared.bus over two real Zenoh peers on loopback, multicast scouting off.

One peer listens on a free TCP port, the other connects to it. Nothing is
timed: every wait polls a condition under a generous deadline.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import pytest

from shared import topics
from shared.bus import Bus, HealthChange, Latest, Subscription, zenoh_config
from shared.messages import Detection, Observation, VehicleReset, VehicleState
from shared.settings import BusSettings
from tests.zenoh_peers import (
    DEADLINE_S,
    async_wait_until,
    routed,
    wait_routed,
    wait_until,
)

pytestmark = pytest.mark.timeout(90)

OBS_KEY = topics.observation("robot0")
ALL_OBS = topics.observation(topics.ANY_ROBOT)


def _obs(seq: int, text: str = "a landing pad, clear") -> Observation:
    return Observation(seq=seq, task="land", text=text)


async def next_item(sub: Subscription[Observation]) -> Observation:
    got = await asyncio.wait_for(anext(sub), DEADLINE_S)
    return got.message


@pytest.mark.parametrize("direction", ["listener->connector", "connector->listener"])
async def test_typed_round_trip(listener: Bus, connector: Bus, direction: str) -> None:
    pub, sub_bus = (
        (listener, connector) if direction.startswith("listener") else (connector, listener)
    )
    sent = Observation(
        seq=7,
        task="land on the pad",
        text="a red box on the landing pad",
        detections=(Detection(label="box", confidence=0.9, where="on the pad"),),
    )
    with sub_bus.subscribe(ALL_OBS, Observation) as sub:
        await routed(pub, sub_bus)
        before = time.monotonic()
        pub.publish(OBS_KEY, sent)
        got = await asyncio.wait_for(anext(sub), DEADLINE_S)
    assert got.key == OBS_KEY
    assert got.message == sent
    assert isinstance(got.message, Observation)
    assert got.received_at >= before
    assert sub.decode_errors == 0 and sub.dropped == 0


async def test_full_queue_drops_oldest(listener: Bus, connector: Bus) -> None:
    sub = connector.subscribe(ALL_OBS, Observation, maxsize=2)
    await routed(listener, connector)
    for seq in range(1, 6):
        listener.publish(OBS_KEY, _obs(seq))
    await async_wait_until(lambda: sub.dropped + sub.qsize() == 5, "all 5 samples to arrive")
    assert sub.received == 5
    assert sub.dropped == 3
    assert [(await next_item(sub)).seq for _ in range(2)] == [4, 5]
    assert sub.qsize() == 0
    sub.close()


async def test_malformed_payload_is_counted_and_skipped(listener: Bus, connector: Bus) -> None:
    sub = connector.subscribe(ALL_OBS, Observation)
    await routed(listener, connector)
    listener.session.put(OBS_KEY, b"{not json")
    listener.session.put(OBS_KEY, json.dumps({"seq": -1, "text": ""}).encode())
    listener.publish(OBS_KEY, _obs(1))
    assert (await next_item(sub)).seq == 1
    await async_wait_until(lambda: sub.decode_errors == 2, "both bad samples to be counted")
    listener.publish(OBS_KEY, _obs(2))
    assert (await next_item(sub)).seq == 2
    assert sub.received == 2
    sub.close()


def test_latest_keeps_the_newest(listener: Bus, connector: Bus) -> None:
    latest = connector.latest(ALL_OBS, Observation)
    assert latest.get() is None
    assert latest.age() is None
    wait_routed(listener, connector)
    listener.session.put(OBS_KEY, b"garbage")
    wait_until(lambda: latest.decode_errors == 1, "the garbage to be counted")
    for seq in range(1, 4):
        listener.publish(OBS_KEY, _obs(seq))
    wait_until(lambda: (got := latest.get()) is not None and got.message.seq == 3,
               "the third message")
    got = latest.get()
    assert got is not None
    assert got.key == OBS_KEY
    assert got.message.seq == 3
    assert latest.decode_errors == 1
    assert latest.age(now=got.received_at + 1.5) == pytest.approx(1.5)
    age = latest.age()
    assert age is not None and age >= 0.0
    latest.close()
    latest.close()
    assert latest.get() == got


def test_latest_skips_what_it_could_not_take_in_time(listener: Bus, connector: Bus) -> None:
    """Issue 46: a busy process (control beside CPU hogs, its interpreter's lock held by its
    solver threads) takes messages in slower than they come. A Latest must then skip to the
    newest, not work through a backlog: a per-message callback queue had control's vehicle
    states arriving 1.7 s late, in order, every one. Here taking one in costs 50 ms (a
    slow ``on_update``) and 40 come in a burst: the newest is taken without taking most
    of the others."""
    taken: list[int] = []
    latest: Latest[Observation] | None = None

    def slow() -> None:
        assert latest is not None
        got = latest.get()
        assert got is not None
        taken.append(got.message.seq)
        time.sleep(0.05)

    latest = connector.latest(ALL_OBS, Observation, on_update=slow)
    wait_routed(listener, connector)
    for seq in range(1, 41):
        listener.publish(OBS_KEY, _obs(seq))
    wait_until(lambda: bool(taken) and taken[-1] == 40, "the newest to be taken")
    assert taken == sorted(taken)  # never an older one after a newer
    assert len(taken) < 10, f"worked through a backlog: {taken}"
    latest.close()


def test_latest_goes_on_after_an_on_update_that_raised(listener: Bus, connector: Bus) -> None:
    calls: list[int] = []

    def fails() -> None:
        calls.append(1)
        raise RuntimeError("a waker with a bug")

    latest = connector.latest(ALL_OBS, Observation, on_update=fails)
    wait_routed(listener, connector)
    listener.publish(OBS_KEY, _obs(1))
    wait_until(lambda: len(calls) == 1, "the first message")
    listener.publish(OBS_KEY, _obs(2))
    wait_until(lambda: (got := latest.get()) is not None and got.message.seq == 2,
               "the second message, after the waker raised")
    latest.close()


def test_a_query_carries_a_message_and_is_answered_with_one(
        listener: Bus, connector: Bus) -> None:
    """The vehicle contract's reset: the query carries a VehicleReset, the answer is a
    VehicleState; a query that carries something else gets no answer (logged)."""
    key = topics.vehicle_reset("drone7")
    asked: list[VehicleReset] = []

    def reset(message: VehicleReset) -> VehicleState:
        asked.append(message)
        return VehicleState(robot="drone7", seq=0, position=message.position,
                            velocity=(0.0, 0.0, 0.0))

    listener.serve(key, VehicleReset, reset)
    wait_routed(listener, connector)
    wait_until(lambda: bool(connector.ask(
        key, VehicleState, payload=VehicleReset(robot="drone7", position=(1.0, 2.0, 3.0)))),
        "an answer to the reset")
    assert asked[-1].position == (1.0, 2.0, 3.0)
    [answer] = connector.ask(key, VehicleState,
                             payload=VehicleReset(robot="drone7", position=(4.0, 5.0, 6.0)))
    assert answer.message.position == (4.0, 5.0, 6.0)
    before = len(asked)
    assert connector.ask(key, VehicleState, payload=_obs(1), timeout=0.5) == []
    assert connector.ask(key, VehicleState, timeout=0.5) == []  # no payload at all
    assert len(asked) == before


def test_alive_sees_a_service_until_it_closes(listener: Bus, connector: Bus) -> None:
    wait_until(lambda: "listener" in connector.alive(), "listener's token")
    assert {"listener", "connector"} <= connector.alive()
    listener.close()
    wait_until(lambda: "listener" not in connector.alive(), "listener's token to vanish")
    assert "connector" in connector.alive()


async def test_watch_alive_reports_up_and_down(listener: Bus, connector: Bus) -> None:
    seen: list[HealthChange] = []

    async def until(service: str, alive: bool) -> None:
        async for change in watch:
            seen.append(change)
            if (change.service, change.alive) == (service, alive):
                return
        raise AssertionError("watch ended")

    with connector.watch_alive() as watch:
        await asyncio.wait_for(until("listener", True), DEADLINE_S)
        listener.close()
        await asyncio.wait_for(until("listener", False), DEADLINE_S)
    assert all(isinstance(change.received_at, float) for change in seen)


@pytest.mark.parametrize("closer", ["subscription", "bus"])
async def test_close_ends_a_blocked_iterator(connector: Bus, closer: str) -> None:
    sub = connector.subscribe(ALL_OBS, Observation)

    async def drain() -> list[Observation]:
        return [got.message async for got in sub]

    task = asyncio.create_task(drain())
    for _ in range(5):
        await asyncio.sleep(0)
    assert not task.done()
    if closer == "bus":
        connector.close()
    else:
        sub.close()
    assert await asyncio.wait_for(task, DEADLINE_S) == []
    assert sub.closed
    with pytest.raises(StopAsyncIteration):
        await anext(sub)
    sub.close()
    connector.close()


def test_sample_after_the_loop_closed_is_ignored(
    listener: Bus, connector: Bus, capfd: pytest.CaptureFixture[str]
) -> None:
    async def make() -> Subscription[Observation]:
        return connector.subscribe(ALL_OBS, Observation)

    sub = asyncio.run(make())  # the loop is closed when this returns
    wait_routed(listener, connector)
    listener.publish(OBS_KEY, _obs(1))
    wait_until(lambda: sub.received == 1, "the callback to run")
    sub.close()
    assert "Traceback" not in capfd.readouterr().err


def test_publish_after_close_raises_and_close_is_idempotent(connector: Bus) -> None:
    connector.close()
    connector.close()
    assert connector.closed
    with pytest.raises(RuntimeError):
        connector.publish(OBS_KEY, _obs(1))


def _conf(settings: BusSettings, key: str) -> object:
    return json.loads(zenoh_config(settings).get_json(key))


def test_zenoh_config_from_settings() -> None:
    settings = BusSettings(
        zenoh_mode="client", zenoh_connect=["tcp/127.0.0.1:7447"], zenoh_listen=[]
    )
    assert _conf(settings, "mode") == "client"
    assert _conf(settings, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _conf(settings, "scouting/multicast/enabled") is False
    assert _conf(BusSettings(zenoh_multicast=True), "scouting/multicast/enabled") is True


def test_zenoh_config_file_then_explicit_settings(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        "{ mode: 'client', // a JSON5 comment\n"
        "  connect: { endpoints: ['tcp/10.0.0.1:7447'] },\n"
        "  scouting: { multicast: { enabled: true } } }\n"
    )
    from_file = BusSettings(zenoh_config=path)
    assert _conf(from_file, "mode") == "client"
    assert _conf(from_file, "connect/endpoints") == ["tcp/10.0.0.1:7447"]
    assert _conf(from_file, "scouting/multicast/enabled") is True
    overridden = BusSettings(
        zenoh_config=path,
        zenoh_mode="peer",
        zenoh_multicast=False,
        zenoh_connect=["tcp/127.0.0.1:7448"],
    )
    assert _conf(overridden, "mode") == "peer"
    assert _conf(overridden, "connect/endpoints") == ["tcp/127.0.0.1:7448"]
    assert _conf(overridden, "scouting/multicast/enabled") is False


def test_a_missing_zenoh_config_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / "gone.json5"
    with pytest.raises(ValueError, match=f"AESOP_ZENOH_CONFIG: cannot read {path}: No such"):
        zenoh_config(BusSettings(zenoh_config=path))
