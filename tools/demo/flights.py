"""``aesop demo``: the paper's hardware scenarios flown by the whole stack.

It brings the stack up (:mod:`tools.stack.up`, logs under ``<out>/logs``),
builds the nominal cache of the hardware scene over REST (every combination of
up to 4 nominal detections, each with its detections), calibrates it split-conformal
(top-1 scores; observations with detections judged by the combined p-value), then
flies each scenario of :data:`tools.scenes.hardware.SCENARIOS`: move the simulated
vehicle (its own process, ``aesop serve sim``) to the start, reset the control loop
there, publish the scripted ``Observation``s at the loop rate, and record what comes
back over Zenoh (states, requests, decisions, events) until the flight's time is up
(22 s of the scene's time, longer when an anomaly came late: until its T has come due).
Then it judges each flight on the simulator's truth (its ``/v1/trace``: where the
vehicle really flew, not where the loop believed it was), with the state's age at
the loop's ticks and the set-points' age at the vehicle, prints the summary table and
writes the report.

:func:`fly_scenarios` is the same cache building and flying against a stack
that is already up (the browser test flies one scenario while a page watches).
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import shlex
import signal
import textwrap
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from services.control.client import ControlClient
from services.control.core.scenario import Scenario, load_scenario
from services.embedding.client import EmbeddingClient
from services.reasoner.client import ReasonerClient
from services.sim.client import SimClient
from services.sim.judge import count_violations, over_limits
from shared import topics
from shared.bus import Bus, Subscription
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    ReasonerDecision,
    ReasonerRequest,
)
from shared.process import file_sink
from shared.settings import BusSettings
from tools import progress
from tools.recording.record import Background, Totals
from tools.scenes.hardware import (
    SCENARIOS,
    DemoScenario,
    build_scene_cache,
    camera_observation,
    observation_text,
)
from tools.stack.acl import MONITOR, robot_user
from tools.stack.up import (
    DETECTOR_CACHE,
    FAKE_LLM_LATENCY_S,
    Stack,
    StackOptions,
    StackPlan,
    plan_stack,
    write_token,
)
from tools.stack.up import (
    hardware_scenario as hardware_path,
)

from .k import (
    SCENE_FILE,
    KChoice,
    control_k,
    how_to_fly,
    k_record,
    measure_k,
    scene_with_k,
)
from .report import (
    WIDTH,
    decisions_text,
    ended_in,
    flight_facts,
    flight_measures,
    judge,
    stories_text,
    summary_tables,
    verdict_line,
    what_happened,
    write_report,
)
from .vehicles import BusVehicle, FlightVehicle, SimVehicle

FLIGHT_S = 22.0  # simulated seconds per scenario: the way in, T = 10 s after the anomaly, settling
SETTLE_S = 3.0  # simulated seconds after a late anomaly's T, to come to rest in the region
ROUTE_TIMEOUT_S = 60.0
STALE_WAIT_S = 0.8  # the control loop's verdicts go stale after 0.5 s by default
CAMERA_PERIOD_S = 0.1  # observations at 10 Hz (the paper's detector ran at 18.8 Hz)
MAX_ANSWER_CHARS = 1000  # of the model's answer, in the report


def run_stack_demo(options: StackOptions, environ: Mapping[str, str], out: Path, *,
                   model: str | None = None, table: bool = True, keep_up: bool = False
                   ) -> dict[str, Any]:
    """Up, the scenarios flown and judged, the report written; then down, or with
    ``keep_up`` supervised as ``aesop up`` supervises its stack (:meth:`Stack.watch`) until
    Ctrl-C or a service dies (``result["stack_stopped"]`` says which, and how)."""
    scenario = load_scenario(options.scenario)
    plan = plan_stack(options, environ, secrets.token_urlsafe(24))
    stack = Stack(plan, file_sink(out / "logs"))
    signal.signal(signal.SIGTERM, _interrupt)
    started = time.monotonic()
    try:
        stack.claim()  # the data dir and the ports first: another stack's token stays its own
        # as `aesop up` keeps it: a generated token in <data dir>/admin-token (0600), so the
        # dashboard's address can be opened (the token is never printed)
        token_file = write_token(options.data_dir, plan.token) if plan.token_generated else None
        progress.step(f"starting the stack (logs in {out / 'logs'})")
        stack.start()
        k = None
        if plan.local_model is not None:  # a model nobody has timed here: K from it first
            k, scenario = fly_with_k(stack, plan, options, environ, scenario, out)
        dashboard = plan.url("dashboard")
        if dashboard:
            _say(f"dashboard: {dashboard_login(dashboard, token_file)}  (watch the flights "
                 "live; opened once, the browser keeps a session)")
        if len(plan.robots) > 1:
            progress.step(f"flying {len(plan.robots)} robots at once: "
                          + ", ".join(f"{r} {FLEET_ORDER[i % len(FLEET_ORDER)]}"
                                      for i, r in enumerate(plan.robots)))
            result, flights = fly_fleet(plan, scenario=scenario, model=model,
                                        record_dir=out / "recordings")
        else:
            result, flights = fly_scenarios(plan, scenario=scenario, model=model,
                                            robot=plan.robot, record_dir=out / "recordings")
        result.update(scene=scenario.name, rate_hz=1.0 / scenario.dt, llm=llm_line(plan, k),
                      wall_s=round(time.monotonic() - started, 1), dashboard=dashboard)
        if k is not None:
            result["k"] = k_record(k)
        progress.step("writing the report")
        report = write_report(out, result, flights, scenario)
        if table:
            progress.out(summary_text(f"{scenario.name}, {result['llm']}", result, report)
                         + ("" if k is None else "\n" + decisions_text(result))
                         + ("" if not dashboard else
                            "\n" + dashboard_text(dashboard, token_file, keep_up)))
        else:
            _say(f"report: {report}")
        if keep_up:
            _say("the stack stays up" + (f" (dashboard: {dashboard_login(dashboard, token_file)})"
                                         if dashboard else "") + "; Ctrl-C stops it")
            progress.step("the stack is up until Ctrl-C")
            died = stack.watch()  # as `aesop up`: a child that dies is started again
            if died is not None:
                _say(f"{died}; stopping the stack")
                result["stack_stopped"] = died
        return result
    except KeyboardInterrupt:
        _say("interrupted")
        raise
    finally:
        stack.stop()


def dashboard_login(url: str, token_file: Path | None) -> str:
    """The dashboard's address with the admin token, as a shell expands it: read from the
    stack's token file (or ``$AESOP_ADMIN_TOKEN``, where the token came from), never the
    token itself. Opened once, the dashboard keeps a session cookie."""
    token = "$AESOP_ADMIN_TOKEN" if token_file is None else \
        f"$(cat {shlex.quote(str(token_file))})"
    return f"{url}/?token={token}"


def dashboard_text(url: str, token_file: Path | None, keep_up: bool) -> str:
    """The summary's lines about the dashboard: how to open it, and for how long it runs."""
    where = ("with AESOP_ADMIN_TOKEN set in that shell" if token_file is None else
             f"the admin token is in {token_file}, readable by you only")
    lines = [f"dashboard: {dashboard_login(url, token_file)}",
             textwrap.fill(f"(open it once, e.g. xdg-open \"<that address>\": {where}; the "
                           "browser then keeps a session)", WIDTH, initial_indent="  ",
                           subsequent_indent="   ", break_on_hyphens=False)]
    if not keep_up:
        lines.append("  (stopped with the demo; `aesop demo --keep-up` leaves it running)")
    return "\n".join(lines)


@dataclass(frozen=True)
class Attached:
    """A stack that is already up (docker compose, or another machine's `aesop up`): where
    its services answer, the admin token, and this robot's Zenoh session (its camera)."""

    embedding_url: str
    control_url: str
    sim_url: str | None  # None: any vehicle on the bus (:class:`.vehicles.BusVehicle`)
    token: str
    bus: BusSettings  # the robot's user: its observations, as its camera publishes them
    reasoner_url: str | None = None  # K measured on the model it asks (--measure-k)
    compose: bool = True  # started by compose (else `aesop up`): how control gets a scene


def run_attached_demo(stack: Attached, out: Path, *, names: Sequence[str] | None = None,
                      model: str | None = None, table: bool = True) -> dict[str, Any]:
    """``aesop demo --attach``: the hardware scenarios (``names``, default all) flown against
    ``stack``, whose control loop flies the hardware scene with its simulator (or any
    vehicle on the bus); the cache built over REST, each flight judged on the vehicle's
    truth, the report in ``out``. With ``stack.reasoner_url``, K is measured on the model
    first (:func:`attached_k`) and the flights judged as a real model's (on safety)."""
    scenario = load_scenario(hardware_path())
    demos = SCENARIOS if names is None else tuple(demo_scenario(n) for n in names)
    started = time.monotonic()
    k, detector = (None, None) if stack.reasoner_url is None else \
        attached_k(stack, scenario, model, out)
    result, flights = asyncio.run(fly_robot(stack.embedding_url, stack.control_url,
                                            stack.sim_url, stack.token, stack.bus, scenario,
                                            model, demos, real_model=k is not None,
                                            detector=detector))
    result.update(scene=scenario.name, rate_hz=1.0 / scenario.dt,
                  llm="the stack's" if k is None else k.pop("llm"),
                  wall_s=round(time.monotonic() - started, 1), dashboard=None)
    if k is not None:
        result["k"] = k
    progress.step("writing the report")
    report = write_report(out, result, flights, scenario)
    if table:
        progress.out(summary_text(f"{scenario.name}, attached to {stack.control_url}", result,
                                  report) + ("" if k is None else "\n" + decisions_text(result)))
    else:
        _say(f"report: {report}")
    return result


def attached_k(stack: Attached, scenario: Scenario, model: str | None, out: Path
               ) -> tuple[dict[str, Any], dict[str, Any]]:
    """``aesop demo --attach --measure-k``: K measured on the model the stack's reasoner
    asks, as ``aesop demo --llm local`` measures it (:func:`.k.measure_k`); but the stack's
    control loop is not ours to restart, so the flights have the K it flies (:func:`.k.control_k`),
    and where the K chosen is another, the scene with it is written to ``out`` and the
    record says how to fly it (:func:`.k.how_to_fly`). What the report keeps of it
    (:func:`.k.k_record`, and ``llm``: the model asked), and the detector's cache built."""
    assert stack.reasoner_url is not None
    built: dict[str, Any] = {}

    def fly(names: Sequence[str], until: threading.Event | None) -> dict[str, Any]:
        result, _ = asyncio.run(fly_robot(
            stack.embedding_url, stack.control_url, stack.sim_url, stack.token, stack.bus,
            scenario, model, tuple(demo_scenario(n) for n in names), real_model=True,
            until=until, detector=built.get("detector")))
        built.setdefault("detector", result["detector"])
        return result

    asked, flown = asyncio.run(_attached_llm(stack))
    choice = measure_k(scenario, stack.reasoner_url, stack.token, fly)
    k_s, why = control_k(flown, scenario)
    record = k_record(choice) | {"flown_s": k_s, "control": why,
                                 "llm": f"{asked}, K = {k_s:g} s (control's)"}
    _say(why)
    if choice.k_s != k_s:
        path = scene_with_k(hardware_path(), choice.k_s, out / SCENE_FILE)
        path.chmod(0o644)  # control's user in a container reads it (uid 10001)
        todo, command = how_to_fly(path, stack.compose)
        record |= {"later": f"the K chosen is not the loop's: answers later than {k_s:g} s "
                            "end as the control loop's fallback",
                   "scene_file": str(path), "to_fly_chosen": [todo, command]}
        _say(f"{record['later']}; to fly K = {choice.k_s:g} s (written to {path}), {todo}\n"
             f"  {command}")
    return record, built["detector"]


async def _attached_llm(stack: Attached) -> tuple[str, str]:
    """The model the stack's reasoner asks (its primary backend) and the scene its control
    loop names."""
    assert stack.reasoner_url is not None
    async with ReasonerClient(stack.reasoner_url, token=stack.token, timeout_s=30) as reasoner:
        primary = (await reasoner.backends()).backends[0]
    async with ControlClient(stack.control_url, token=stack.token, timeout_s=30) as control:
        flown = (await control.state()).scenario
    return f"{primary.model} at {primary.base_url}", flown


def summary_text(about: str, result: dict[str, Any], report: Path) -> str:
    """What the terminal shows once the flights are flown: the tables, what happened in a
    flight that did not end as expected, the verdict and where the report is."""
    return (f"\nAESOP demo — {about}\n\n{summary_tables(result['scenarios'])}\n"
            f"{stories_text(result['scenarios'])}"
            f"\n{verdict_line(result)} ({result['wall_s']:.0f} s)\nreport: {report}")


def _interrupt(*_: object) -> None:
    raise KeyboardInterrupt


def fly_with_k(stack: Stack, plan: StackPlan, options: StackOptions,
               environ: Mapping[str, str], scenario: Scenario, out: Path
               ) -> tuple[KChoice, Scenario]:
    """Measure K on the served model (:func:`.k.measure_k`: timed while the robot flies
    the nominal scenario again and again) and, when the scene can keep it, give the
    control loop that K: it is started again on the scene with that K. The K chosen and
    the scene now flown."""
    url = plan.url("reasoner")
    assert url is not None

    def fly(names: Sequence[str], until: threading.Event | None) -> dict[str, Any]:
        return fly_scenarios(plan, names, scenario=scenario, robot=plan.robot, until=until)[0]

    choice = measure_k(scenario, url, plan.token, fly)
    if choice.k_s != scenario.consensus_s:
        path = scene_with_k(plan.scenario, choice.k_s, out / "data" / "scene-with-k.yaml")
        again = plan_stack(replace(options, scenario=path), environ, plan.token,
                           passwords=lambda _: dict(plan.passwords))
        stack.replace(next(s for s in again.services if s.name == "control"))
        scenario = load_scenario(path)
    return choice, scenario


def llm_line(plan: StackPlan, k: KChoice | None) -> str:
    if plan.fake_llm:
        return f"the fake LLM, {FAKE_LLM_LATENCY_S:g} s per answer"
    if plan.local_model is None:
        return "the configured LLM backend"
    return (f"{plan.local_model.alias} on llama.cpp's server"
            + ("" if k is None else f", K = {k.k_s:g} s"
               + (" (measured)" if k.calibrated else " (the scene's)")))


def _say(message: str) -> None:
    progress.say(message)


# --------------------------------------------------------------------------- the flights


def demo_scenario(name: str) -> DemoScenario:
    """The demo scenario called ``name``, or whose name starts with ``name-`` ("2a")."""
    for demo in SCENARIOS:
        if name in (demo.name, demo.name.split("-", 1)[0]):
            return demo
    raise KeyError(f"no demo scenario {name!r}: {', '.join(d.name for d in SCENARIOS)}")


def fly_scenarios(plan: StackPlan, names: Sequence[str] | None = None, *,
                  scenario: Scenario | None = None, model: str | None = None,
                  robot: str | None = None, record_dir: Path | None = None,
                  until: threading.Event | None = None
                  ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Build and calibrate the cache on the running stack of ``plan``, then fly the named
    demo scenarios (all of :data:`SCENARIOS` by default) in turn, as ``aesop demo`` does.

    ``scenario`` defaults to the scene the stack's services were given, ``robot`` to the
    one they serve. With ``record_dir``, each flight's topics are recorded there as
    ``<scenario>.mcap`` (by the read-only ``monitor`` user). Returns the result (``ok``,
    one row per scenario, the detector's calibration) and each flight's states. With a
    real model (the plan serves one) a wrong decision is reported, not failed: a flight
    passes when it ends safely where its decision sent it (:func:`.report.judge`).
    ``until``: no further flight starts once it is set (flights flown only as load: none
    is reported on the terminal).
    """
    if scenario is None:
        scenario = load_scenario(plan.scenario)
    demos = SCENARIOS if names is None else tuple(demo_scenario(n) for n in names)
    robot = robot or plan.robot
    settings = plan.bus_settings(robot_user(plan.robot), robot=robot)
    recorders = None if record_dir is None else Recorders(
        plan.bus_settings(MONITOR, robot=robot), record_dir, robot)
    return asyncio.run(fly_robot(plan.url("embedding"), plan.url("control"), plan.url("sim"),
                                 plan.token, settings, scenario, model, demos, recorders,
                                 real_model=plan.local_model is not None, until=until))


# what each robot of a fleet flies, in turn (aesop demo --robots N): the anomalies first
FLEET_ORDER = ("2a", "2b", "3", "1")


def fly_fleet(plan: StackPlan, *, scenario: Scenario, model: str | None = None,
              record_dir: Path | None = None, airborne: threading.Event | None = None
              ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``aesop demo --robots N``: build and calibrate the cache once, then every robot of
    ``plan`` flies its scenario (:data:`FLEET_ORDER`, one each) at the same time, with
    its own control loop, vehicle and camera; the detector replicas share the robots. The
    rows carry their robot; the flights are keyed ``<robot>: <scenario>``. ``airborne`` is
    set once every robot's flight has started."""
    jobs = [(robot, demo_scenario(FLEET_ORDER[i % len(FLEET_ORDER)]))
            for i, robot in enumerate(plan.robots)]
    started: set[str] = set()

    def on_start(robot: str) -> None:
        started.add(robot)
        if airborne is not None and len(started) == len(jobs):
            airborne.set()

    async def fleet() -> list[tuple[dict[str, Any], dict[str, np.ndarray]]]:
        detector = await scene_cache(plan.url("embedding"), plan.token, model)
        return await asyncio.gather(*(
            fly_robot(None, *plan.robot_urls(robot), plan.token,
                      plan.bus_settings(robot_user(robot), robot=robot), scenario, model,
                      [demo], None if record_dir is None else Recorders(
                          plan.bus_settings(MONITOR, robot=robot), record_dir, robot,
                          prefix=f"{robot}-"),
                      real_model=plan.local_model is not None, detector=detector,
                      on_start=partial(on_start, robot))
            for robot, demo in jobs))

    flown = asyncio.run(fleet())
    rows = [{"robot": robot, **row} for (robot, _), (result, _) in zip(jobs, flown, strict=True)
            for row in result["scenarios"]]
    flights = {f"{robot}: {name}": states for (robot, _), (_, theirs) in
               zip(jobs, flown, strict=True) for name, states in theirs.items()}
    return {"ok": all(r["outcome"] == "ok" for r in rows), "scenarios": rows,
            "detector": flown[0][0]["detector"], "state_rate_hz": flown[0][0]["state_rate_hz"],
            "robots": list(plan.robots)}, flights


@dataclass(frozen=True)
class Recorders:
    """Where and as whom each flight is recorded."""

    settings: BusSettings
    folder: Path
    robot: str
    prefix: str = ""  # of the files' names: a fleet's robots record into one folder

    def of(self, demo: DemoScenario) -> Background:
        self.folder.mkdir(parents=True, exist_ok=True)
        return Background(self.settings, self.folder / f"{self.prefix}{demo.name}.mcap",
                          robot=self.robot)


@dataclass
class Recorder:
    """Everything of one flight that arrived over Zenoh."""

    states: list[ControlState] = field(default_factory=list)
    requests: list[ReasonerRequest] = field(default_factory=list)
    decisions: list[ReasonerDecision] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    detector_alarms: int = 0  # anomalous verdicts during the flight
    flagged_at: list[float] = field(default_factory=list)  # when each came (the loop's t)
    recording: bool = False

    @property
    def t(self) -> float:
        return self.states[-1].t if self.states else 0.0


async def scene_cache(embedding_url: str | None, token: str, model: str | None
                       ) -> dict[str, Any]:
    """Build and calibrate the detector's cache of the scene; what it is."""
    assert embedding_url
    progress.step("building and calibrating the detector's cache")
    async with EmbeddingClient(embedding_url, token=token, timeout_s=60) as client:
        info, cal = await build_scene_cache(client, DETECTOR_CACHE, model=model, say=_say)
    return {"size": info.size, "k": info.k, "calibration": cal.model_dump(mode="json")}


async def fly_robot(embedding_url: str | None, control_url: str | None, sim_url: str | None,
                    token: str, settings: BusSettings, scenario: Scenario, model: str | None,
                    demos: Sequence[DemoScenario] = SCENARIOS,
                    recorders: Recorders | None = None, *, real_model: bool = False,
                    until: threading.Event | None = None,
                    detector: dict[str, Any] | None = None,
                    on_start: Callable[[], None] | None = None
                    ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """One robot's flights (``settings.robot``), the cache built first unless
    ``detector`` says it is; ``on_start``: called as each flight starts. The vehicle is
    the simulator at ``sim_url``, or with None any vehicle on the bus
    (:class:`.vehicles.BusVehicle`)."""
    assert control_url
    if detector is None:
        detector = await scene_cache(embedding_url, token, model)
    rows, flights = [], {}
    state_rate_hz: float | None = None
    with Bus.open(settings, "demo") as bus:
        robot = settings.robot
        rec = Recorder()
        verdicts = bus.subscribe(topics.anomaly(robot), AnomalyVerdict, maxsize=1024)
        tasks = [
            asyncio.create_task(_collect(bus.subscribe(topics.anomaly(robot), AnomalyVerdict,
                                                       maxsize=1024), rec, _on_verdict)),
            asyncio.create_task(_collect(bus.subscribe(topics.state(robot), ControlState,
                                                       maxsize=4096), rec, _on_state)),
            asyncio.create_task(_collect(bus.subscribe(topics.reasoner_request(robot),
                                                       ReasonerRequest), rec, _on_request)),
            asyncio.create_task(_collect(bus.subscribe(topics.reasoner_decision(robot),
                                                       ReasonerDecision), rec, _on_decision)),
            asyncio.create_task(_collect(bus.subscribe(topics.events(robot), Event, maxsize=1024),
                                         rec, _on_event)),
        ]
        camera = Camera(bus, robot, CAMERA_PERIOD_S, rec, scenario.start_center)
        tasks.append(asyncio.create_task(camera.run()))
        try:
            await _first_verdict(verdicts)
            async with contextlib.AsyncExitStack() as stack:
                control = await stack.enter_async_context(
                    ControlClient(control_url, token=token, timeout_s=60))
                vehicle: FlightVehicle = BusVehicle(bus, robot) if sim_url is None else \
                    SimVehicle(await stack.enter_async_context(
                        SimClient(sim_url, token=token, timeout_s=60)))
                pilots = Pilots(control, vehicle)
                for n, demo in enumerate(demos, 1):
                    if until is not None and until.is_set():
                        break
                    if until is None and on_start is None:  # (not load, not a fleet's)
                        progress.step(f"flight {demo.name}", n, len(demos))
                    row, states = await fly(pilots, camera, verdicts, rec, demo, scenario,
                                            None if recorders is None else recorders.of(demo),
                                            real_model=real_model, on_start=on_start)
                    rows.append(row)
                    flights[demo.name] = states
                    if until is None:
                        _say(f"  {demo.name}: {row['outcome']}" + (
                            "" if row["outcome"] == "ok" else f"\n    {row['what_happened']}"))
                state_rate_hz = await vehicle.rate_hz()
            add_time_lost(rows)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
    return {"ok": all(r["outcome"] == "ok" for r in rows), "scenarios": rows,
            "detector": detector, "state_rate_hz": state_rate_hz}, flights


class Camera:
    """Publishes the scene's detections as ``Observation``s once per control tick."""

    def __init__(self, bus: Bus, robot: str, period_s: float, rec: Recorder,
                 home: Sequence[float]) -> None:
        self.bus, self.robot, self.period_s, self.rec = bus, robot, period_s, rec
        self.home = tuple(home)
        self.scene: DemoScenario = SCENARIOS[0]
        self.flying = False
        self.paused = False  # publishes nothing (a new flight is being set up)
        self.seq = 0

    def detections(self) -> tuple[str, ...]:
        """What the camera sees from where the robot is (before a flight: its start)."""
        here = self.rec.states[-1].x if self.flying and self.rec.states else self.home
        return self.scene.detections(here)

    async def run(self) -> None:
        while True:
            if not self.paused:
                self.seq += 1
                seen = self.detections()
                self.bus.publish(topics.observation(self.robot),
                                 camera_observation(observation_text(seen), self.seq,
                                                    self.robot))
            await asyncio.sleep(self.period_s)


@dataclass(frozen=True)
class Pilots:
    """What a demo flight is started through: the control loop and the vehicle."""

    control: ControlClient
    vehicle: FlightVehicle

    async def new_flight(self, camera: Camera, start: Sequence[float],
                         timeout_s: float = ROUTE_TIMEOUT_S) -> None:
        """A new flight from ``start``, as an operator starts one: the camera off (so the
        loop, once reset, waits: no fresh verdict), the loop reset (it sends nothing
        while it waits, the vehicle holds), the vehicle moved to ``start``; once the loop
        sees it there, the camera on again: the detector answers and the flight starts."""
        camera.paused = True
        await asyncio.sleep(STALE_WAIT_S)  # the newest verdict goes stale
        await self.control.reset()
        await self.vehicle.reset(start)
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                state = (await self.control.state()).state
                if state is not None and state.mode == "waiting" and float(np.linalg.norm(
                        np.asarray(state.x[:3]) - np.asarray(start))) < 0.05:
                    return
                if time.monotonic() > deadline:
                    raise RuntimeError("the control loop does not see the vehicle at the "
                                       "start")
                await asyncio.sleep(0.05)
        finally:
            camera.paused = False


async def fly(pilots: Pilots, camera: Camera, verdicts: Subscription[AnomalyVerdict],
              rec: Recorder, demo: DemoScenario, scenario: Scenario,
              recorder: Background | None = None, *, real_model: bool = False,
              on_start: Callable[[], None] | None = None
              ) -> tuple[dict[str, Any], np.ndarray]:
    camera.scene, camera.flying = demo, False
    await _calm(camera, verdicts)
    if recorder is None:
        return await _fly(pilots, camera, rec, demo, scenario, real_model, on_start)
    await asyncio.to_thread(recorder.start)
    try:
        row, states = await _fly(pilots, camera, rec, demo, scenario, real_model, on_start)
    finally:  # a failed flight's recording is finished (indexed) too
        totals = await asyncio.to_thread(recorder.stop)
    row["recording"] = recording_row(totals, recorder.out)
    return row, states


async def _fly(pilots: Pilots, camera: Camera, rec: Recorder, demo: DemoScenario,
               scenario: Scenario, real_model: bool,
               on_start: Callable[[], None] | None = None
               ) -> tuple[dict[str, Any], np.ndarray]:
    rec.recording = False
    rec.states, rec.requests, rec.decisions, rec.events = [], [], [], []
    rec.detector_alarms, rec.flagged_at = 0, []
    start = [float(v) for v in scenario.start_center]
    await pilots.new_flight(camera, start)
    rec.recording = True
    camera.flying = True
    if on_start is not None:
        on_start()
    wall = time.monotonic()
    deadline = wall + 3 * FLIGHT_S + 30
    while rec.t < flight_end(rec, scenario):
        if time.monotonic() > deadline:
            raise RuntimeError(f"{demo.name}: the control loop published no state for a while")
        await asyncio.sleep(0.05)
    camera.flying = False
    rec.recording = False
    truth, setpoints = await pilots.vehicle.flown()
    return summarize(rec, demo, scenario, time.monotonic() - wall, truth, setpoints,
                     real_model=real_model)


def flight_end(rec: Recorder, scenario: Scenario) -> float:
    """When a flight is over (simulated s): :data:`FLIGHT_S`, or later when an anomaly came
    late (a verdict sent late on a loaded machine raises one too): its T has to come due
    before where the robot ends is judged."""
    t_anom = max((s.t_anom for s in rec.states if s.t_anom is not None), default=0.0)
    return min(max(FLIGHT_S, t_anom + scenario.horizon_s + SETTLE_S), 2 * FLIGHT_S)


def recording_row(totals: Totals, path: Path) -> dict[str, Any]:
    """What a flight's recording holds, and what recording it cost (per second)."""
    seconds = max(totals.seconds, 1e-9)
    return {"file": f"{path.parent.name}/{path.name}", "messages": totals.messages,
            "bytes": totals.bytes, "file_bytes": path.stat().st_size,
            "seconds": round(totals.seconds, 2),
            "messages_per_s": round(totals.messages / seconds, 1),
            "bytes_per_s": round(totals.bytes / seconds),
            "cpu_percent": round(100 * totals.cpu_s / seconds, 1)}


def add_time_lost(rows: list[dict[str, Any]]) -> None:
    """Scenario 3's landing against the nominal flight's (same start, same route)."""
    landed = {r["name"].split("-", 1)[0]: r.get("landed_s") for r in rows}
    nominal, lost = landed.get("1"), landed.get("3")
    for row in rows:
        if row["name"].startswith("3-") and lost is not None and nominal is not None:
            row["time_lost_s"] = round(lost - nominal, 2)


def summarize(rec: Recorder, demo: DemoScenario, scenario: Scenario, wall_s: float,
              truth: np.ndarray, setpoints: Mapping[str, float | int | None], *,
              real_model: bool = False) -> tuple[dict[str, Any], np.ndarray]:
    """A flight's row, judged on the vehicle's ``truth`` (its trace, 12-state rows) and the
    loop's inputs; ``setpoints``: their age at the vehicle (the simulator's summary);
    ``real_model``: a wrong decision is reported (``decision_right``), not failed."""
    states = truth if len(truth) else np.array([s.x for s in rec.states])
    inputs = np.array([s.u for s in rec.states])
    ages = [s.state_age_s * 1000.0 for s in rec.states if s.state_age_s is not None]
    # the anomaly behind the flight's last decision (a late verdict may have raised one before)
    anomaly_at = next((s.t_anom for s in reversed(rec.states) if s.t_anom is not None), None)
    ids = {r.request_id: r for r in rec.requests}
    answered = [d for d in rec.decisions if d.request_id in ids]
    decided = answered[-1] if answered else None  # the decision the flight ended with
    decision: str | None = None
    source: str | None = None
    if decided is not None:
        labels = {o.index: o.label for o in ids[decided.request_id].options}
        decision, source = labels.get(decided.choice, str(decided.choice)), decided.source
    fallback = next((e for e in rec.events if e.kind == "fallback"), None)
    if fallback is not None:  # the loop committed at K without (or before) a decision
        chosen = fallback.data.get("chosen")
        decision = next((r.label for r in scenario.regions if r.index == chosen), str(chosen))
        source = "control fallback at K"
    elif decision not in (None, "continue") and rec.states and rec.states[-1].chosen is None:
        # a region chosen for an episode that had ended before the answer came (the
        # detector was back from its silence): the loop flew on and never acted on it
        decision, source = None, f"{source}, late: not acted on"
    ended = ended_in(states[-1], scenario) if len(states) else None
    violations = count_violations(states, inputs, scenario)
    facts = flight_facts(demo, scenario, rec.states, rec.requests, rec.decisions, rec.events,
                         rec.flagged_at)
    problems = judge(demo, ended=ended, detector_alarms=rec.detector_alarms,
                     anomaly_at_s=anomaly_at, decision=decision, violations=violations,
                     scenario=scenario if real_model else None, facts=facts)
    measures = flight_measures([s.t for s in rec.states], np.array([s.x for s in rec.states]),
                               [s.mode for s in rec.states], scenario.goal, anomaly_at)
    row = {"name": demo.name, "expected": demo.expected, "outcome": "; ".join(problems) or "ok",
           "ended_in": ended, "anomaly_at_s": None if anomaly_at is None else round(anomaly_at, 2),
           "decision": decision, "decision_source": source,
           "decision_right": None if demo.expected_decision is None
           else decision == demo.expected_decision,
           "answer": None if decided is None else decided.answer[:MAX_ANSWER_CHARS],
           "constraint_violations": violations,
           # which limits, how far past (None: not a finite number)
           "over_limits": {name: [rows, _round(worst) if np.isfinite(worst) else None]
                           for name, (rows, worst)
                           in over_limits(states, inputs, scenario).items()},
           "duration_s": round(rec.states[-1].t, 2) if rec.states else 0.0,
           "wall_s": round(wall_s, 2),
           "decision_latency_ms": None if decided is None else round(decided.latency_ms, 1),
           "reasoner_requests": len(rec.requests),
           "stale_verdict_alarms": sum(e.kind == "verdict_stale" for e in rec.events),
           "stale_state_alarms": sum(e.kind == "state_stale" for e in rec.events),
           "state_age_ms": _percentiles(ages),
           "setpoint_age_ms": [setpoints.get("age_p50_ms"), setpoints.get("age_p99_ms"),
                               setpoints.get("age_max_ms")],
           "approach_altitude_m": _round(measures.approach_altitude_m),
           "landed_s": _round(measures.landed_s),
           "speeds": [_round(measures.speed_before_m_s), _round(measures.speed_waiting_m_s),
                      _round(measures.speed_after_m_s)],
           "closest_to_goal_m": _round(measures.closest_to_goal_m),
           "time_lost_s": None,
           "anomalous_verdicts": rec.detector_alarms,
           "what_happened": what_happened(demo, facts, ended=ended, decision=decision,
                                          source=source),
           "rationale": None if decided is None else decided.rationale[-300:]}
    return row, states


async def _calm(camera: Camera, verdicts: Subscription[AnomalyVerdict]) -> None:
    """Wait for a nominal verdict on an observation published from now on."""
    since = camera.seq
    deadline = time.monotonic() + ROUTE_TIMEOUT_S
    while time.monotonic() < deadline:
        try:
            got = await asyncio.wait_for(anext(verdicts), 1.0)
        except TimeoutError:
            continue
        if got.message.seq > since and not got.message.is_anomaly:
            return
    raise RuntimeError("no nominal verdict for the nominal scene: is the cache calibrated?")


async def _first_verdict(verdicts: Subscription[AnomalyVerdict]) -> None:
    try:
        await asyncio.wait_for(anext(verdicts), ROUTE_TIMEOUT_S)
    except TimeoutError:
        raise RuntimeError("no anomaly verdict over Zenoh: the embedding worker is not "
                           "reachable") from None


async def _collect(sub: Subscription[Any], rec: Recorder,
                   on: Callable[[Recorder, Any], None]) -> None:
    async for got in sub:
        if rec.recording:
            on(rec, got.message)


def _on_state(rec: Recorder, msg: ControlState) -> None:
    if rec.states or msg.t < 0.5:  # a tick from before the reset is not this flight's
        rec.states.append(msg)


def _on_verdict(rec: Recorder, msg: AnomalyVerdict) -> None:
    rec.detector_alarms += int(msg.is_anomaly)
    if msg.is_anomaly:
        rec.flagged_at.append(rec.t)


def _on_request(rec: Recorder, msg: ReasonerRequest) -> None:
    rec.requests.append(msg)


def _on_decision(rec: Recorder, msg: ReasonerDecision) -> None:
    rec.decisions.append(msg)


def _on_event(rec: Recorder, msg: Event) -> None:
    rec.events.append(msg)


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 2)


def _percentiles(values: Sequence[float]) -> list[float | None]:
    """p50, p99 and max, rounded (None for none)."""
    if not values:
        return [None, None, None]
    return [round(float(np.percentile(values, 50)), 2), round(float(np.percentile(values, 99)), 2),
            round(float(max(values)), 2)]
