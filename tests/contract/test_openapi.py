"""Each service's ``/openapi.json`` is its contract: Schemathesis finds no mismatch.

Every service runs as a real process (uvicorn, the real model, real Zenoh), and
Schemathesis' own CLI generates requests from the published schema: bounded
(``--max-examples``, a fixed seed, so a failure replays) and with every check
(server errors, undocumented status codes and content types, answers that do not
match their schema, schema-invalid requests accepted, schema-valid requests
refused, the Allow header, auth). The few schema-valid requests a service may
still refuse are listed per operation, with the reason, in ``schemathesis.toml``.
"""

from __future__ import annotations

import contextlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

from shared.process import ServiceProcess, free_port

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

TOKEN = "contract-token-0123456789"
CONFIG = Path(__file__).with_name("schemathesis.toml")
SCHEMATHESIS = Path(sys.executable).with_name("st")
EXAMPLES = 30  # per operation and phase: about 2,500 requests over the six services
# the run checks what an answer says, not how soon: beside the compose test's image builds
# on two cores, one cache create (a SQLite write, a model load) took over Schemathesis'
# default 10 s, once as "Read timed out" and once (11.7 s) as its `max_response_time`
# check, which `--checks all` turns on; both limits are this
REQUEST_TIMEOUT_S = 60
SEED = 1
QUADROTOR = Path(__file__).resolve().parents[2] / "deploy" / "ros2" / "quadrotor.yaml"


def service_args(service: str, tmp_path: Path) -> tuple[list[str], dict[str, str]]:
    env = {"AESOP_ADMIN_TOKEN": TOKEN, "AESOP_ZENOH_LISTEN": f"tcp/127.0.0.1:{free_port()}"}
    args = ["serve", service]
    if service == "embedding":
        args += ["--data-dir", str(tmp_path / "data")]
        env["AESOP_EMBEDDING_ZENOH_WORKER"] = "false"
    if service == "reasoner":  # nothing listens there: every backend call fails fast
        env["AESOP_REASONER_LLM_BASE_URL"] = f"http://127.0.0.1:{free_port()}/v1"
    if service == "ros2":
        env["AESOP_ROS2_CONFIG"] = str(QUADROTOR)
    return args, env


@pytest.mark.parametrize("service", ["embedding", "reasoner", "control", "dashboard", "sim",
                                     "ros2"])
def test_the_service_keeps_its_published_contract(service: str, tmp_path: Path) -> None:
    args, env = service_args(service, tmp_path)
    port = free_port()
    with contextlib.ExitStack() as upstream:
        if service == "dashboard":  # its batch review goes to a real embedding service
            up_args, up_env = service_args("embedding", tmp_path)
            up_port = free_port()
            upstream.enter_context(ServiceProcess(
                [*up_args, "--port", str(up_port)], port=up_port, env=up_env,
                log_path=tmp_path / "embedding.log"))
            env["AESOP_DASHBOARD_EMBEDDING_URL"] = f"http://127.0.0.1:{up_port}"
        upstream.enter_context(ServiceProcess([*args, "--port", str(port)], port=port,
                                              env=env, log_path=tmp_path / f"{service}.log"))
        run = subprocess.run(
            [str(SCHEMATHESIS), "--no-color", "--config-file", str(CONFIG), "run",
             f"http://127.0.0.1:{port}/openapi.json", "--checks", "all",
             "--max-examples", str(EXAMPLES), "--seed", str(SEED),
             "--request-timeout", str(REQUEST_TIMEOUT_S),
             "--max-response-time", str(REQUEST_TIMEOUT_S),
             "--header", f"Authorization: Bearer {TOKEN}"],
            capture_output=True, text=True, timeout=500, cwd=tmp_path)  # its caches go there
    assert run.returncode == 0, f"{service}:\n{run.stdout[-12000:]}\n{run.stderr[-2000:]}"
    counts = re.search(r"(\d+) generated, (\d+) passed", run.stdout)
    assert counts is not None and int(counts[1]) == int(counts[2]) > 0, run.stdout[-3000:]


def keywords_json_schema_lacks(schema: object, path: str = "") -> list[str]:
    """Paths of pydantic constraint names left in a JSON Schema (``ge``, ``max_length``...):
    keywords a validator of the schema ignores, so the published limit would be lost."""
    raw = {"ge", "le", "gt", "lt", "min_length", "max_length", "allow_inf_nan", "strict"}
    found: list[str] = []
    if isinstance(schema, dict):
        for key, value in schema.items():
            if key in raw and path.rsplit("/", 1)[-1] != "properties":
                found.append(f"{path}/{key}")
            found += keywords_json_schema_lacks(value, f"{path}/{key}")
    elif isinstance(schema, list):
        for i, value in enumerate(schema):
            found += keywords_json_schema_lacks(value, f"{path}/{i}")
    return found


def test_published_schemas_use_json_schema_keywords_only() -> None:
    from services.control.core.scenario import load_scenario
    from services.control.schemas import RegionsAnswer, RegionsBody, ResetAnswer, ResetBody, State
    from services.dashboard.fleet import FleetSnapshot
    from services.dashboard.model import Snapshot
    from services.embedding.api import create_app as embedding_app
    from services.embedding.settings import EmbeddingSettings
    from services.reasoner.api import create_app as reasoner_app
    from services.reasoner.settings import ReasonerSettings
    from services.ros2.schemas import BridgeAnswer
    from services.sim.api import create_app as sim_app
    from services.sim.settings import SimSettings

    schemas: dict[str, object] = {
        "embedding": embedding_app(EmbeddingSettings(zenoh_worker=False)).openapi(),
        "reasoner": reasoner_app(ReasonerSettings()).openapi(),
        "sim": sim_app(SimSettings(), load_scenario()).openapi(),
        **{m.__name__: m.model_json_schema() for m in
           (RegionsBody, ResetBody, State, RegionsAnswer, ResetAnswer, Snapshot,
            FleetSnapshot, BridgeAnswer)},
    }
    assert keywords_json_schema_lacks(schemas) == []
    assert keywords_json_schema_lacks({"k": {"anyOf": [{"ge": 1}]}}) == ["/k/anyOf/0/ge"]
