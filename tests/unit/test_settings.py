"""Settings per service: shared ``AESOP_*`` names, ``AESOP_<SERVICE>_*`` for the rest, and
the environment ``aesop up`` writes for a child reading back what it was given."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from pydantic import ValidationError
from pydantic_settings import BaseSettings

from services.control.settings import ControlSettings
from services.dashboard.settings import DashboardLimits, DashboardSettings
from services.embedding.settings import EmbeddingLimits, EmbeddingSettings, EmbeddingTuning
from services.reasoner.settings import Hedge, ReasonerSettings
from services.sim.settings import SimSettings
from shared.bus import zenoh_config
from shared.settings import BusSettings, env_names, read_settings, to_env
from tools.fakes.llm import FakeLLMServiceSettings

SERVICES: list[type[BaseSettings]] = [EmbeddingSettings, ReasonerSettings, ControlSettings,
                                      SimSettings, DashboardSettings, FakeLLMServiceSettings]


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.startswith("AESOP_") or name == "OPENAI_API_KEY":
            monkeypatch.delenv(name)


def test_shared_names_reach_every_service_and_the_rest_is_each_services_own(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AESOP_ROBOT", "r7")
    monkeypatch.setenv("AESOP_ZENOH_CONNECT", "tcp/10.0.0.1:7447")
    monkeypatch.setenv("AESOP_ADMIN_TOKEN", "t" * 20)
    monkeypatch.setenv("AESOP_CONTROL_PORT", "9100")
    monkeypatch.setenv("AESOP_EMBEDDING_PORT", "9200")
    monkeypatch.setenv("AESOP_REASONER_FALLBACK", "rank")
    monkeypatch.setenv("AESOP_CONTROL_FALLBACK", "2")
    monkeypatch.setenv("AESOP_DASHBOARD_LIMITS__TRAIL", "500")
    control, embedding = ControlSettings(), EmbeddingSettings()
    reasoner, dashboard = ReasonerSettings(), DashboardSettings()
    for s in (control, embedding, reasoner, dashboard):
        assert s.robot == "r7" and s.zenoh_connect == ["tcp/10.0.0.1:7447"]
        assert s.admin_token is not None and s.admin_token.get_secret_value() == "t" * 20
    assert (control.port, embedding.port, reasoner.port, dashboard.port) == (9100, 9200, 8002,
                                                                            8080)
    assert reasoner.fallback == "rank" and control.fallback == 2 and dashboard.limits.trail == 500


def test_a_name_of_another_service_is_not_read(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AESOP_FALLBACK", "rank")  # the old flat name: nobody reads it
    monkeypatch.setenv("AESOP_PORT", "9999")
    monkeypatch.setenv("AESOP_REASONER_PORT", "9002")
    assert ReasonerSettings().fallback == "first_recovery"
    assert ControlSettings().port == 8003 and ReasonerSettings().port == 9002


@pytest.mark.parametrize("cls", SERVICES, ids=lambda c: c.__name__)
def test_every_field_has_one_name_of_its_service_or_a_shared_one(cls: type[BaseSettings]
                                                                 ) -> None:
    shared = {"robot", "zenoh_mode", "zenoh_listen", "zenoh_connect", "zenoh_multicast",
              "zenoh_config", "zenoh_user", "zenoh_password", "zenoh_password_file",
              "zenoh_tls_ca", "zenoh_tls_cert", "zenoh_tls_key", "zenoh_id", "admin_token",
              "admin_token_file", "data_dir",
              "log_level", "log_format"}
    prefix = str(cls.model_config["env_prefix"])
    assert prefix.startswith("AESOP_") and prefix != "AESOP_"
    for name in cls.model_fields:
        first = env_names(cls, name)[0]
        if name in shared:
            assert first == f"AESOP_{name.upper()}", name
        else:
            assert first == f"{prefix}{name.upper()}", name


def test_what_aesop_up_writes_is_read_back_the_same() -> None:
    given = [
        ControlSettings(port=9103, rate_hz=20.0, scenario=Path("/tmp/s.yaml"), fallback=2,
                        start_position=(0.0, 1.0, 1.5), robot="r2", admin_token="k" * 16,
                        zenoh_connect=["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]),
        ReasonerSettings(llm_base_url="http://llm:1/v1", fallback="rank",
                         fallback_ranks={"holding zone": 1, "blue box": 2},
                         hedge=Hedge(model="m", after_s=1.5)),
        EmbeddingSettings(detector_cache="quadrotor", tuning=EmbeddingTuning(microbatch=False),
                          data_dir=Path("/d")),
        DashboardSettings(limits=DashboardLimits(trail=100), zenoh_multicast=True),
    ]
    for settings in given:
        environ = to_env(settings)
        assert all(name.startswith("AESOP_") for name in environ)
        with pytest.MonkeyPatch.context() as mp:
            for name, value in environ.items():
                mp.setenv(name, value)
            assert type(settings)() == settings


def test_a_bad_value_is_refused_naming_the_field() -> None:
    with pytest.raises(ValidationError, match="rate_hz"):
        ControlSettings(rate_hz=-1.0)
    with pytest.raises(ValidationError, match="fallback"):
        ControlSettings(fallback=0)


def test_an_old_or_misspelt_name_is_pointed_out() -> None:
    from tools.cli import warn_unknown_settings

    said = warn_unknown_settings({"AESOP_LLM_BASE_URL": "http://llm/v1", "AESOP_ROBOT": "r1",
                                  "AESOP_CONTROL_RATE_HZ": "20", "AESOP_CONTROL_RATEHZ": "5",
                                  "AESOP_NOTHING_LIKE_IT_AT_ALL_XYZ": "1", "PATH": "/bin"})
    assert said[0] == ("aesop: AESOP_CONTROL_RATEHZ is not a setting of any service "
                       "(did you mean AESOP_CONTROL_RATE_HZ?)")
    assert said[1] == ("aesop: AESOP_LLM_BASE_URL is not a setting of any service "
                       "(did you mean AESOP_REASONER_LLM_BASE_URL?)")
    assert said[2] == "aesop: AESOP_NOTHING_LIKE_IT_AT_ALL_XYZ is not a setting of any service"
    assert len(said) == 3


def test_the_variables_of_compose_and_the_image_scripts_are_not_called_misspelt() -> None:
    # `AESOP_DOCKER_ROOT=... make image` then any aesop command (the suite's services) said
    # "AESOP_DOCKER_ROOT is not a setting of any service", in plain text under JSON logs
    import re

    from tools.cli import warn_unknown_settings

    root = Path(__file__).resolve().parents[2]
    files = [root / "docker-compose.yml", root / "Makefile", *root.glob("deploy/*.yml"),
             *root.glob("deploy/docker/*.sh")]
    used = {name for f in files for name in re.findall(r"\$\{?(AESOP_[A-Z0-9_]+)", f.read_text())}
    assert {"AESOP_DOCKER_ROOT", "AESOP_BASE_IMAGE", "AESOP_SECRETS"} <= used
    assert warn_unknown_settings(dict.fromkeys(used, "x")) == []


def test_a_knob_moved_into_a_group_is_pointed_to_its_new_name() -> None:
    from tools.cli import warn_unknown_settings

    said = warn_unknown_settings({"AESOP_EMBEDDING_MAX_JOBS": "2",
                                  "AESOP_REASONER_LLM_STREAM": "false",
                                  "AESOP_SIM_STATE_RATE_HZ": "50", "AESOP_SIM_TRACE_HZ": "5",
                                  "AESOP_EMBEDDING_LIMITS__MAX_JOB": "2",
                                  "AESOP_EMBEDDING_LIMITS__MAX_JOBS": "2"})
    assert said == [
        "aesop: AESOP_EMBEDDING_LIMITS__MAX_JOB is not a setting of any service "
        "(did you mean AESOP_EMBEDDING_LIMITS__MAX_JOBS?)",
        "aesop: AESOP_EMBEDDING_MAX_JOBS is not a setting of any service "
        "(did you mean AESOP_EMBEDDING_LIMITS__MAX_JOBS?)",
        "aesop: AESOP_REASONER_LLM_STREAM is not a setting of any service "
        "(did you mean AESOP_REASONER_REQUEST__STREAM?)",
        "aesop: AESOP_SIM_STATE_RATE_HZ is not a setting of any service "
        "(did you mean AESOP_SIM_REPORTS__RATE_HZ?)",
        "aesop: AESOP_SIM_TRACE_HZ is not a setting of any service "
        "(did you mean AESOP_SIM_TRACE__HZ?)"]


def test_a_group_is_set_as_json_or_one_knob_at_a_time() -> None:
    environ = {"AESOP_EMBEDDING_LIMITS": '{"max_items": 7, "max_jobs": 3}',
               "AESOP_EMBEDDING_LIMITS__MAX_JOBS": "2", "AESOP_EMBEDDING_TUNING__MICROBATCH": "no"}
    settings = read_settings(EmbeddingSettings, environ)
    assert (settings.limits.max_items, settings.limits.max_jobs) == (7, 2)  # the knob wins
    assert settings.limits.max_text_chars == EmbeddingLimits().max_text_chars  # the rest kept
    assert settings.tuning.microbatch is False
    with pytest.raises(ValidationError, match=r"limits\.max_job\b"):  # no such knob
        read_settings(EmbeddingSettings, {"AESOP_EMBEDDING_LIMITS": '{"max_job": 3}'})
    with pytest.raises(ValidationError, match=r"reports\.drop_rate"):
        read_settings(SimSettings, {"AESOP_SIM_REPORTS__DROP_RATE": "1.5"})


# the detector's two past 15: its shared store and its name among replicas (issue 30)
@pytest.mark.parametrize(("cls", "most"), [(EmbeddingSettings, 17), (ReasonerSettings, 14),
                                           (ControlSettings, 11), (SimSettings, 10),
                                           (DashboardSettings, 6)], ids=lambda c: str(c))
def test_each_service_reads_few_variables_of_its_own(cls: type[BaseSettings], most: int) -> None:
    """Operators set what is theirs; tuning knobs live in groups of one variable each."""
    prefix = str(cls.model_config["env_prefix"])
    own = {env_names(cls, name)[0] for name in cls.model_fields}
    assert len({n for n in own if n.startswith(prefix)}) <= most


def test_the_detectors_store_is_a_postgresql_url_and_its_replica_one_key_chunk() -> None:
    with pytest.raises(ValidationError, match="AESOP_EMBEDDING_STORE is a PostgreSQL URL"):
        read_settings(EmbeddingSettings, {"AESOP_EMBEDDING_STORE": "mysql://db/aesop"})
    with pytest.raises(ValidationError, match="AESOP_EMBEDDING_REPLICA is one Zenoh key chunk"):
        read_settings(EmbeddingSettings, {"AESOP_EMBEDDING_REPLICA": "site/a"})
    url = "postgresql://aesop:secret@db:5432/aesop"
    settings = read_settings(EmbeddingSettings, {"AESOP_EMBEDDING_STORE": url,
                                                 "AESOP_EMBEDDING_REPLICA": "site-a"})
    assert settings.store is not None and settings.store.get_secret_value() == url
    assert "secret" not in repr(settings) and settings.replica_name() == "site-a"
    assert read_settings(EmbeddingSettings, {"AESOP_EMBEDDING_STORE": ""}).store is None


def test_mutual_tls_files_become_zenohs_tls_block(tmp_path: Path) -> None:
    """Issue 41: a session that leaves its host presents a certificate of the stack's CA."""
    for name in ("ca.pem", "me.pem", "me-key.pem"):
        (tmp_path / name).write_text("-----BEGIN-----\n")
    settings = read_settings(BusSettings, {
        "AESOP_ZENOH_CONNECT": "tls/server.lan:7447", "AESOP_ZENOH_MODE": "client",
        "AESOP_ZENOH_TLS_CA": str(tmp_path / "ca.pem"),
        "AESOP_ZENOH_TLS_CERT": str(tmp_path / "me.pem"),
        "AESOP_ZENOH_TLS_KEY": str(tmp_path / "me-key.pem")})
    conf = zenoh_config(settings)
    assert json.loads(conf.get_json("transport/link/tls/connect_certificate")) == \
        str(tmp_path / "me.pem")
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) == \
        str(tmp_path / "ca.pem")
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True


@pytest.mark.parametrize(("given", "says"), [
    ({"AESOP_ZENOH_TLS_CERT": "c.pem"}, "AESOP_ZENOH_TLS_KEY"),
    ({"AESOP_ZENOH_TLS_CERT": "c.pem", "AESOP_ZENOH_TLS_KEY": "k.pem"}, "AESOP_ZENOH_TLS_CA"),
])
def test_tls_files_that_cannot_work_are_refused_naming_the_variable(
        given: dict[str, str], says: str) -> None:
    with pytest.raises(ValidationError, match=says):
        read_settings(BusSettings, given)


def test_a_missing_tls_file_is_named_before_any_handshake(tmp_path: Path) -> None:
    (tmp_path / "ca.pem").write_text("x")
    settings = BusSettings(zenoh_tls_ca=tmp_path / "ca.pem", zenoh_tls_cert=tmp_path / "gone.pem",
                           zenoh_tls_key=tmp_path / "gone-key.pem")
    with pytest.raises(ValueError, match="AESOP_ZENOH_TLS_CERT: cannot read .*gone.pem"):
        zenoh_config(settings)


def test_each_process_its_own_zenoh_id_over_the_shared_client_file(tmp_path: Path) -> None:
    """Issue 42: compose.fleet's robots share a client file; one ID is one session at a
    router, so the ID comes from AESOP_ZENOH_ID, over the file's."""
    client = tmp_path / "control.json5"
    client.write_text('{id: "ae5003", connect: {timeout_ms: 60000}}')
    settings = read_settings(BusSettings, {"AESOP_ZENOH_CONFIG": str(client),
                                           "AESOP_ZENOH_ID": "ae5103"})
    assert json.loads(zenoh_config(settings).get_json("id")) == "ae5103"
    with pytest.raises(ValidationError, match="zenoh_id|AESOP_ZENOH_ID"):
        read_settings(BusSettings, {"AESOP_ZENOH_ID": "robot-1"})  # not hex


def test_the_admin_token_from_a_file_a_compose_secret(tmp_path: Path) -> None:
    """Issue 42: compose hands the token as a file, out of `docker inspect`'s environment."""
    token = tmp_path / "admin-token"
    token.write_text("t" * 32 + "\n")
    settings = read_settings(ControlSettings, {"AESOP_ADMIN_TOKEN_FILE": str(token)})
    assert settings.admin_token is not None and settings.admin_token.get_secret_value() == "t" * 32
    for env, says in [({"AESOP_ADMIN_TOKEN_FILE": str(tmp_path / "gone")},
                       "AESOP_ADMIN_TOKEN_FILE: cannot read"),
                      ({"AESOP_ADMIN_TOKEN_FILE": str(token), "AESOP_ADMIN_TOKEN": "u" * 32},
                       "not both")]:
        with pytest.raises(ValidationError, match=says):
            read_settings(ControlSettings, env)
    token.write_text("short\n")
    with pytest.raises(ValidationError, match="at least 16"):
        read_settings(ControlSettings, {"AESOP_ADMIN_TOKEN_FILE": str(token)})


def test_the_admin_token_file_from_the_process_environment(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """As `aesop serve` reads it in a container: the class's own environment source."""
    token = tmp_path / "admin-token"
    token.write_text("v" * 32 + "\n")
    monkeypatch.setenv("AESOP_ADMIN_TOKEN_FILE", str(token))
    settings = ControlSettings(host="0.0.0.0")
    assert settings.admin_token is not None and settings.admin_token.get_secret_value() == "v" * 32
    settings.check_exposure()  # off loopback, with the token from the file


def test_the_reasoners_llm_key_from_a_file(tmp_path: Path) -> None:
    """Issue 43: compose hands the LLM key as a file; a key in the environment wins."""
    key = tmp_path / "llm.key"
    key.write_text("sk-from-file\n")
    settings = read_settings(ReasonerSettings, {"AESOP_REASONER_LLM_API_KEY_FILE": str(key)})
    assert settings.backends()[0].api_key == "sk-from-file"
    given = read_settings(ReasonerSettings, {"AESOP_REASONER_LLM_API_KEY_FILE": str(key),
                                             "AESOP_REASONER_LLM_API_KEY": "sk-env"})
    assert given.backends()[0].api_key == "sk-env"
    with pytest.raises(ValidationError, match="AESOP_REASONER_LLM_API_KEY_FILE: cannot read"):
        read_settings(ReasonerSettings, {"AESOP_REASONER_LLM_API_KEY_FILE": str(tmp_path / "x")})
