"""The reasoner's pieces together: a real prompt, ``aesop serve fake-llm`` over HTTP, the
strict parser. The hardware scenarios get the paper's decisions."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from services.reasoner.parsing import ParseError, parse_decision
from services.reasoner.prompts import build_messages, load_template
from shared.messages import Option
from shared.process import ServiceProcess, free_port

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

OPTIONS = (
    Option(index=0, label="continue"),
    Option(index=1, label="alternative landing site", description="land on the blue box"),
    Option(index=2, label="holding zone", description="hover in the designated holding zone"),
)
SCENES = {
    "a red box on the ground\na drill on the ground\na keyboard on the ground": 0,
    "a red box on the ground\na blue box on the ground\na quadrotor on the red box": 1,
    "a quadrotor on the red box\na quadrotor on the blue box": 2,
}


@pytest.fixture(scope="module")
def fake_llm(tmp_path_factory: pytest.TempPathFactory) -> str:
    port = free_port()
    log = Path(tmp_path_factory.mktemp("fake-llm")) / "fake-llm.log"
    with ServiceProcess(["serve", "fake-llm", "--port", str(port), "--profile", "fixed",
                         "--fixed-s", "0.05"], port=port, log_path=log) as proc:
        yield proc.url


@pytest.mark.parametrize(("observation", "expected"), SCENES.items())
@pytest.mark.parametrize("variant", ["cot", "single"])
def test_scenarios_round_trip(fake_llm: str, observation: str, expected: int,
                              variant: str) -> None:
    messages = build_messages(load_template("quadrotor"), task="landing on the red box",
                              observation=observation, options=OPTIONS, variant=variant)
    r = httpx.post(f"{fake_llm}/v1/chat/completions", timeout=10,
                   json={"model": "fake", "messages": messages})
    assert r.status_code == 200, r.text
    text = r.json()["choices"][0]["message"]["content"]
    assert parse_decision(text, [o.index for o in OPTIONS]).choice == expected


def test_garbage_is_a_parse_error_never_a_guess(fake_llm: str) -> None:
    messages = build_messages(load_template("quadrotor"), task="landing on the red box",
                              observation="a quadrotor on the red box", options=OPTIONS)
    for kind in ("noanswer", "two", "badindex"):
        r = httpx.post(f"{fake_llm}/v1/chat/completions", timeout=10,
                       json={"model": f"fake-garbage-{kind}", "messages": messages})
        with pytest.raises(ParseError):
            parse_decision(r.json()["choices"][0]["message"]["content"], [0, 1, 2])
