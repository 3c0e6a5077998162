"""Issue 26, finding 8: the reasoner's decisions leave by K from a process of their own
(the deadline keeper), whatever the service's main process is doing, and the keeper and
the service live and die together. A real ``aesop serve reasoner`` against a stalling
fake LLM, a real Zenoh peer playing the control loop."""

from __future__ import annotations

import os
import secrets
import signal
from collections.abc import Iterator
from pathlib import Path

import httpx
import psutil
import pytest

from shared import topics
from shared.bus import Bus, Latest
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest
from shared.process import ServiceProcess, free_port
from tests.zenoh_peers import wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

WAIT_S = 60.0  # generous: nothing here is timed, only waited for
OPTIONS = (Option(index=0, label="continue"),
           Option(index=1, label="alternative landing site", description="the blue box"),
           Option(index=2, label="holding zone", description="hover and wait"))


@pytest.fixture(scope="module")
def stalling_llm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    port = free_port()
    log = Path(tmp_path_factory.mktemp("llm")) / "fake-llm.log"
    with ServiceProcess(["serve", "fake-llm", "--port", str(port), "--profile", "stall"],
                        port=port, log_path=log) as proc:
        yield f"{proc.url}/v1"


@pytest.fixture
def reasoner(tmp_path: Path, stalling_llm: str, listener: Bus, endpoint: str
             ) -> Iterator[ServiceProcess]:
    port = free_port()
    env = {"AESOP_ADMIN_TOKEN": secrets.token_urlsafe(24), "AESOP_ZENOH_CONNECT": endpoint,
           "AESOP_REASONER_LLM_BASE_URL": stalling_llm}
    with ServiceProcess(["serve", "reasoner", "--port", str(port), "--data-dir",
                         str(tmp_path)], port=port, env=env,
                        log_path=tmp_path / "reasoner.log") as proc:
        wait_until(lambda: "reasoner" in listener.alive(), "the reasoner on the bus", WAIT_S)
        yield proc


def request(request_id: str, deadline_s: float = 0.5) -> ReasonerRequest:
    return ReasonerRequest(robot="drone7", request_id=request_id, deadline_s=deadline_s,
                           observation=Observation(robot="drone7", seq=1,
                                                   task="landing on the red box",
                                                   text="a quadrotor on the red box"),
                           options=OPTIONS)


def keeper_of(service: ServiceProcess) -> psutil.Process:
    """The service's deadline keeper: its child started by multiprocessing's spawn."""
    found: list[psutil.Process] = []

    def look() -> bool:
        found[:] = [c for c in psutil.Process(service.pid).children()
                    if "spawn_main" in " ".join(c.cmdline())]
        return len(found) == 1

    wait_until(look, "the reasoner's deadline keeper", WAIT_S)
    return found[0]


def ask(listener: Bus, decisions: Latest[ReasonerDecision], request_id: str) -> ReasonerDecision:
    listener.publish(topics.reasoner_request("drone7"), request(request_id))

    def answered() -> bool:
        got = decisions.get()
        return got is not None and got.message.request_id == request_id

    wait_until(answered, f"the decision for {request_id}", WAIT_S)
    got = decisions.get()
    assert got is not None
    return got.message


def test_a_frozen_service_still_answers_by_the_deadline(
        reasoner: ServiceProcess, listener: Bus) -> None:
    """The service's main process is stopped (as a long collection or a starved core would
    hold it) while the LLM stalls: the timeout fallback still leaves, from the keeper. When
    the one process both asked the LLM and published, nothing left until it ran again."""
    with listener.latest(topics.reasoner_decision("drone7"), ReasonerDecision) as decisions:
        keeper_of(reasoner)
        os.kill(reasoner.pid, signal.SIGSTOP)
        try:
            decision = ask(listener, decisions, "frozen")
            assert psutil.Process(reasoner.pid).status() == psutil.STATUS_STOPPED
        finally:
            os.kill(reasoner.pid, signal.SIGCONT)
    assert decision.source == "timeout" and decision.choice == 1
    assert decision.robot == "drone7" and decision.latency_ms > 0


def test_a_keeper_that_dies_is_started_again(reasoner: ServiceProcess, listener: Bus) -> None:
    with listener.latest(topics.reasoner_decision("drone7"), ReasonerDecision) as decisions:
        first = keeper_of(reasoner)
        assert ask(listener, decisions, "before").source == "timeout"
        first.kill()
        first.wait(WAIT_S)
        wait_until(lambda: keeper_of(reasoner).pid != first.pid, "another keeper", WAIT_S)
        wait_until(lambda: httpx.get(f"{reasoner.url}/readyz").status_code == 200,
                   "the reasoner ready again", WAIT_S)
        assert ask(listener, decisions, "after").source == "timeout"
    assert "the deadline keeper exited" in reasoner.log_tail(200)


def test_the_keeper_goes_with_the_service(reasoner: ServiceProcess, listener: Bus) -> None:
    """A service killed outright takes its keeper with it: no orphan keeps the reasoner's
    token on the bus, answering with nothing behind it."""
    keeper = keeper_of(reasoner)
    os.kill(reasoner.pid, signal.SIGKILL)
    keeper.wait(WAIT_S)
    wait_until(lambda: "reasoner" not in listener.alive(), "the reasoner gone from the bus",
               WAIT_S)
