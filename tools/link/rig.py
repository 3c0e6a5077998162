"""A server and a robot on two hosts of one machine, a lossy link between them: what
``aesop bench link`` and ``tests/integration/test_link.py`` fly.

:class:`Rig` does what a robot team does, with the commands the docs give: ``aesop zenoh
certs`` (the server's address in its certificate), ``aesop up --role server`` here, and
``aesop up --role robot`` in the robot's network namespace (:mod:`.netns`), its router
linked to the server's through a :class:`~tools.link.proxy.FaultProxy` on the veth link
(delay, jitter, stalls, cuts). A second proxy, impaired alike, carries the robot's HTTP
writes to the server's detector. The cache the detector scores against is built once.

:meth:`Rig.fly` flies one demo scenario under one :class:`Fault` with the robot's
:mod:`.driver`, applies the fault when the driver says the flight is on (or the anomaly
raised), and returns the :class:`Flight`: the judged row (on the vehicle's truth), each
verdict's round trip, when the link came back and when the robot heard the server again,
the writes the server acknowledged and those it then did not have.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import secrets
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import psutil

from services.embedding.client import EmbeddingClient
from shared.client import ServiceError
from shared.process import free_port
from tools.demo.flights import scene_cache
from tools.stack.acl import robot_user, server_users
from tools.stack.certs import write_certs

from .netns import Link, robot_namespace
from .proxy import FaultProxy, Impairment

ROBOT = "robot0"
WRITES_CACHE = "link-writes"
UP_TIMEOUT_S = 420.0  # the server loads and warms its model first
FAULT_AFTER_START_S = 3.0  # into the nominal flight: the robot is on its way in
LINGER_AFTER_HEAL_S = 6.0  # the camera stays on this long after the link returns


@dataclass(frozen=True)
class Fault:
    """What the link does during one flight: a delay (each way, with jitter) throughout,
    and, :data:`FAULT_AFTER_START_S` into the flight, a stall or a cut of that many
    seconds, or a router killed (``aesop up`` starts it again)."""

    name: str
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    stall_s: float = 0.0
    cut_s: float = 0.0
    restart: Literal["server", "robot"] | None = None

    @property
    def impairment(self) -> Impairment:
        return Impairment(self.delay_ms, self.jitter_ms)

    @property
    def event(self) -> bool:
        """Something happens mid-flight (a stall, a cut, a restart), not just a delay."""
        return bool(self.stall_s or self.cut_s or self.restart)


def delay(ms: float, jitter_ms: float = 20.0) -> Fault:
    return Fault(f"delay {ms:g} ms", ms, min(jitter_ms, ms))


# the fault table: every row a flight judged on the vehicle's truth
FAULTS = (delay(0), delay(20), delay(50), delay(100), Fault("stall 1 s", stall_s=1.0),
          Fault("cut 3 s", cut_s=3.0), Fault("cut 30 s", cut_s=30.0),
          Fault("server's router restarted", restart="server"),
          Fault("robot's router restarted", restart="robot"))


@dataclass
class Flight:
    fault: Fault
    scenario: str
    row: dict[str, Any]  # the demo's judged row (outcome "ok": where it should, no violation)
    verdict_ms: list[float]  # each verdict's round trip, observation to verdict, on the robot
    started_at: float | None  # time.monotonic() of the fault's start, the link's return
    back_at: float | None
    heard_at: float | None  # the first verdict after the link came back, of a later observation
    acked: list[str] = field(default_factory=list)  # writes the server answered 2xx
    failed_writes: int = 0
    lost: list[str] = field(default_factory=list)  # acknowledged, then not on the server
    link_kb_s: tuple[float, float] = (0.0, 0.0)  # Zenoh's bytes robot -> server, back, per s
    loop: dict[str, float] = field(default_factory=dict)  # what the loop counted (driver)

    @property
    def unmonitored_ticks(self) -> float:
        """Ticks the loop flew with its verdicts or its vehicle's state stale: each one an
        anomaly (its own count: events said during a router's outage are lost with it)."""
        return self.loop.get("stale_verdict_ticks", 0.0) + self.loop.get("stale_state_ticks",
                                                                          0.0)

    @property
    def reconnect_s(self) -> float | None:
        """From the link's return (a healed cut, a restarted router's kill) to the first
        verdict the robot heard of an observation made after it."""
        if self.back_at is None or self.heard_at is None:
            return None
        return self.heard_at - self.back_at

    @property
    def fallback(self) -> bool:
        return self.row.get("decision_source") == "control fallback at K" \
            or self.loop.get("fallbacks", 0.0) > 0


class Up:
    """One ``aesop up`` process: its output to a log, its URLs once it says it is up."""

    def __init__(self, argv: list[str], env: dict[str, str], log: Path) -> None:
        log.parent.mkdir(parents=True, exist_ok=True)
        self.log = log
        self.proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     start_new_session=True)
        self.urls: dict[str, str] = {}
        self._up = threading.Event()
        threading.Thread(target=self._read, daemon=True, name=f"up-{log.stem}").start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        with open(self.log, "ab") as out:
            for raw in self.proc.stdout:
                out.write(raw)
                out.flush()
                line = raw.decode(errors="replace")
                if found := re.match(r"^  (\S+)\s+((?:https?://|tcp/|tls/)\S+)", line):
                    self.urls[found.group(1)] = found.group(2)
                if line.startswith("Ctrl-C stops everything"):
                    self._up.set()

    def wait_up(self, timeout_s: float = UP_TIMEOUT_S) -> dict[str, str]:
        deadline = time.monotonic() + timeout_s
        while not self._up.wait(1.0):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{self.log.stem} did not come up: "
                                   + "\n".join(self.tail()))
        return self.urls

    def tail(self, lines: int = 40) -> list[str]:
        try:
            return self.log.read_text(errors="replace").splitlines()[-lines:]
        except OSError:
            return []

    def stop(self) -> None:
        """SIGINT (``aesop up`` stops its children), then SIGKILL the group if need be."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


class Rig:
    """The two hosts, the link, the two stacks and the scene's cache (a context manager)."""

    def __init__(self, out: Path, *, name: str = "aesoplink", robot: str = ROBOT,
                 say: Callable[[str], None] = _say) -> None:
        self.out, self.name, self.robot, self.say = out, name, robot, say
        self.token = secrets.token_urlsafe(24)
        self._exit = ExitStack()
        self.link: Link
        self.certs = out / "certs"
        self.zenoh: FaultProxy
        self.http: FaultProxy
        self.server: Up
        self.robot_up: Up
        self.detector: dict[str, Any] = {}

    def __enter__(self) -> Rig:
        try:
            self._start()
        except BaseException:
            self._exit.close()
            raise
        return self

    def __exit__(self, *_: object) -> None:
        self._exit.close()

    def _env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
        return {**env, "AESOP_ADMIN_TOKEN": self.token, "AESOP_ROBOT": self.robot,
                "PYTHONUNBUFFERED": "1"}

    def _start(self) -> None:
        self.link = self._exit.enter_context(robot_namespace(self.name))
        self.say(f"link: this host {self.link.server_ip}, the robot {self.link.robot_ip} "
                 f"(namespace {self.link.namespace})")
        write_certs(self.certs, robots=[self.robot], services=server_users(),
                    server_names=[self.link.server_ip])
        port = free_port()
        aesop = [sys.executable, "-m", "tools.cli", "up"]
        self.say("starting the server (aesop up --role server) ...")
        self.server = Up([*aesop, "--role", "server", "--tls", str(self.certs),
                          "--listen", f"tls/127.0.0.1:{port}", "--random-ports",
                          "--data-dir", str(self.out / "server")], self._env(),
                         self.out / "logs" / "server.log")
        self._exit.callback(self.server.stop)
        urls = self.server.wait_up()
        self.zenoh = self._exit.enter_context(
            FaultProxy((self.link.server_ip, 0), ("127.0.0.1", port), seed=1).start())
        embedding = int(urls["embedding"].rsplit(":", 1)[1])
        self.http = self._exit.enter_context(
            FaultProxy((self.link.server_ip, 0), ("127.0.0.1", embedding), seed=2).start())
        self.say("starting the robot (aesop up --role robot, in its namespace) ...")
        self.robot_up = Up(self.link.run(
            [*aesop, "--role", "robot", "--robot", self.robot,
             "--server", f"{self.link.server_ip}:{self.zenoh.port}",
             "--tls", str(self.certs / robot_user(self.robot)), "--random-ports",
             "--data-dir", str(self.out / "robot")]), self._env(),
            self.out / "logs" / "robot.log")
        self._exit.callback(self.robot_up.stop)
        self.robot_up.wait_up()
        self.say("building the scene's cache on the server ...")
        self.detector = asyncio.run(self._caches(urls["embedding"]))

    async def _caches(self, url: str) -> dict[str, Any]:
        detector = await scene_cache(url, self.token, None)
        async with EmbeddingClient(url, token=self.token, timeout_s=60) as client:
            await client.create_cache(WRITES_CACHE)
        return detector

    def impair(self, impairment: Impairment) -> None:
        for proxy in (self.zenoh, self.http):
            proxy.set(impairment)

    def _cut(self, seconds: float) -> float:
        for proxy in (self.zenoh, self.http):
            proxy.cut()
        time.sleep(seconds)
        for proxy in (self.zenoh, self.http):
            proxy.heal()
        return time.monotonic()

    def _kill_router(self, which: str) -> float:
        """SIGKILL the server's or the robot's router; ``aesop up`` starts it again."""
        for proc in psutil.process_iter(["pid", "cmdline"]):
            argv = proc.info["cmdline"] or []
            role = dict(zip(argv, argv[1:], strict=False)).get("--role")
            if "tools.stack.router" in argv and role == which \
                    and any(str(self.certs) in a for a in argv):
                os.kill(proc.info["pid"], signal.SIGKILL)
                return time.monotonic()
        raise RuntimeError(f"no {which} router running")

    def _apply(self, fault: Fault) -> tuple[float, float]:
        """The fault's event, now: when it began and when the link was back."""
        began = time.monotonic()
        if fault.cut_s:
            return began, self._cut(fault.cut_s)
        if fault.stall_s:
            for proxy in (self.zenoh, self.http):
                proxy.stall(fault.stall_s)
            return began, began + fault.stall_s
        assert fault.restart is not None
        killed = self._kill_router(fault.restart)
        return killed, killed

    def fly(self, fault: Fault, scenario: str) -> Flight:
        """One flight of ``scenario`` ("1", "2a", ...) under ``fault``."""
        self.impair(fault.impairment)
        robot_urls = self.robot_up.urls
        tag = re.sub(r"[^A-Za-z0-9]+", "-", f"{fault.name}-{scenario}-{time.monotonic():.0f}")
        argv = [sys.executable, "-m", "tools.link.driver", "--router", robot_urls["zenoh"],
                "--control", robot_urls["control"], "--sim", robot_urls["sim"],
                "--robot", self.robot, "--scenario", scenario,
                "--detector", json.dumps(self.detector),
                "--writes", f"http://{self.link.server_ip}:{self.http.port}",
                "--writes-cache", WRITES_CACHE, "--tag", tag,
                *(["--linger"] if fault.event else ["--strict"])]
        log = self.out / "logs" / f"driver-{tag}.log"
        before, since = self.zenoh.stats, time.monotonic()
        with open(log, "ab") as err:
            driver = subprocess.Popen(self.link.run(argv), env=self._env(), stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=err, text=True)
        try:
            result, began, back = self._drive(driver, fault)
        finally:
            if driver.poll() is None:
                driver.kill()
            driver.wait(10)
        self.impair(Impairment())
        after, seconds = self.zenoh.stats, time.monotonic() - since
        rates = tuple(round((int(after[k]) - int(before[k])) / 1000 / seconds, 1)
                      for k in ("bytes_up", "bytes_down"))
        verdicts = [(float(o), float(v)) for o, v in result["verdicts"]]
        heard = min((v for o, v in verdicts if back is not None and o > back), default=None)
        flight = Flight(fault, scenario, result["row"], [(v - o) * 1000 for o, v in verdicts],
                        began, back, heard, result["writes"]["acked"],
                        result["writes"]["failed"])
        flight.lost = asyncio.run(self._missing(flight.acked))
        flight.link_kb_s = (rates[0], rates[1])
        flight.loop = {k: float(v) for k, v in result.get("loop", {}).items()}
        return flight

    def _drive(self, driver: subprocess.Popen[str], fault: Fault
               ) -> tuple[dict[str, Any], float | None, float | None]:
        """Read the driver's lines: apply the fault once the flight is on, let it stop
        lingering once the link has been back a while; its result."""
        assert driver.stdout is not None and driver.stdin is not None
        applied: list[tuple[float, float]] = []
        worker: threading.Thread | None = None
        for raw in driver.stdout:  # the driver gives up on a flight that never ends
            line = raw.strip()
            if line.startswith("started") and fault.event and worker is None:
                def later() -> None:
                    time.sleep(FAULT_AFTER_START_S)
                    applied.append(self._apply(fault))
                worker = threading.Thread(target=later, daemon=True)
                worker.start()
            elif line.startswith("flown") and fault.event:
                if worker is not None:
                    worker.join()
                back = applied[0][1] if applied else time.monotonic()
                time.sleep(max(0.0, back + LINGER_AFTER_HEAL_S - time.monotonic()))
                driver.stdin.write("stop\n")
                driver.stdin.flush()
            elif line.startswith("result "):
                result = json.loads(line.removeprefix("result "))
                if not applied:
                    return result, None, None
                return result, *applied[0]
        raise RuntimeError(f"the flight under {fault.name!r} ended without a result "
                           f"(exit {driver.poll()}); see {self.out / 'logs'}")

    async def _missing(self, acked: list[str]) -> list[str]:
        """The acknowledged writes the server does not have."""
        url = self.server.urls["embedding"]
        lost = []
        async with EmbeddingClient(url, token=self.token, timeout_s=30) as client:
            for ident in acked:
                try:
                    await client.experience(WRITES_CACHE, ident)
                except ServiceError as exc:
                    if exc.status != 404:
                        raise
                    lost.append(ident)
        return lost

