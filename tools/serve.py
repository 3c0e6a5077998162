"""``aesop serve SERVICE``: one service in this process, its settings from flags and
``AESOP_*`` variables."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from tools.commands import CliError, control_scenario, ros2_config

if TYPE_CHECKING:
    from shared.settings import ServiceSettings

ExposedSettings = TypeVar("ExposedSettings", bound="ServiceSettings")
# those on the robot's clock: the control loop, the vehicle and the bridge to a ROS 2 one (the
# reasoner favours itself for its deadline, services/reasoner/deciding.py)
FAVOURED = ("control", "sim", "ros2")


def register(sub: argparse._SubParsersAction) -> None:
    serve = sub.add_parser("serve", help="run one service (settings also from AESOP_* env vars)")
    serve.add_argument("service",
                       choices=["embedding", "reasoner", "control", "dashboard", "sim",
                                "ros2", "fake-llm"],
                       help="sim: the simulated vehicle control flies; ros2: the bridge to a "
                            "ROS 2 robot (AESOP_ROS2_CONFIG); fake-llm: an "
                            "OpenAI-compatible test server, see its --help")
    serve.add_argument("--host", help="the address its HTTP API listens on (default "
                       "AESOP_<SERVICE>_HOST, else 127.0.0.1)")
    serve.add_argument("--port", type=int, help="its HTTP port (default AESOP_<SERVICE>_PORT, "
                       "else the service's: 8001 embedding, 8002 reasoner, 8003 control, "
                       "8004 sim, 8005 ros2, 8080 dashboard)")
    serve.add_argument("--data-dir", type=Path, help="where it keeps its files (default "
                       "AESOP_DATA_DIR, else ./data)")
    serve.add_argument("--scenario", default=None,
                       help="control and sim: a bundled scenario (paper, hardware) or a file "
                            "(default: AESOP_CONTROL_SCENARIO or AESOP_SIM_SCENARIO, else "
                            "paper)")
    serve.set_defaults(func=cmd_serve)


def cmd_serve(args: argparse.Namespace) -> int:
    if args.service == "fake-llm":
        from tools.fakes.llm import main as fake_llm

        given = [(flag, v) for flag, v in (("--host", args.host), ("--port", args.port))
                 if v is not None]
        return fake_llm([str(x) for pair in given for x in pair] + args.extra)

    overrides = {k: v for k, v in (("host", args.host), ("port", args.port),
                                   ("data_dir", args.data_dir)) if v is not None}
    if args.scenario is not None and args.service not in ("control", "sim"):
        raise CliError("--scenario: only `aesop serve control` and `aesop serve sim` take a "
                       "scenario")
    if args.service in FAVOURED:
        favour(args.service)
    if args.service == "sim":
        return serve_sim(overrides, args.scenario)
    if args.service == "ros2":
        return serve_ros2(overrides)
    if args.service == "reasoner":
        return serve_reasoner(overrides)
    if args.service == "control":
        return serve_control(overrides, args.scenario)
    if args.service == "dashboard":
        return serve_dashboard(overrides)

    from services.embedding.api import served_app
    from services.embedding.settings import EmbeddingSettings
    from shared.serving import serve

    settings = _exposed(EmbeddingSettings(**overrides))
    if settings.tuning.torch_threads:
        import torch

        torch.set_num_threads(settings.tuning.torch_threads)
    serve(served_app(settings), settings)
    return 0


def serve_reasoner(overrides: dict[str, Any]) -> int:
    from services.reasoner.api import create_app
    from services.reasoner.deciding import keep_up, settle
    from services.reasoner.settings import ReasonerSettings
    from services.reasoner.worker import ReasonerWorker
    from shared.serving import serve

    settings = _exposed(ReasonerSettings(**overrides))
    keep_up()
    serve(create_app(settings, worker_factory=ReasonerWorker.factory(settings),
                     on_started=settle), settings)
    return 0


def favour(service: str) -> None:
    """A process that must act on time (the control loop, the vehicle, the bus) asks for a
    larger share of a busy machine's cores before it starts a thread: its threads inherit
    it (:func:`shared.realtime.favoured`). Without ``CAP_SYS_NICE`` it says so once."""
    from shared.realtime import favoured

    if not favoured():
        print(f"{service}: runs at normal priority (no CAP_SYS_NICE): on a busy machine its "
              "ticks and states may come late", file=sys.stderr, flush=True)


def serve_control(overrides: dict[str, Any], scenario: str | None = None) -> int:
    from services.control.api import create_app
    from services.control.loop import ControlRuntime
    from services.control.service import SERVICE
    from services.control.settings import ControlSettings
    from shared.bus import Bus
    from shared.serving import serve

    if scenario is not None:
        overrides = {**overrides, "scenario": scenario}
    settings = _exposed(ControlSettings(**overrides))
    scene = control_scenario(settings.scenario, flag=scenario is not None)
    try:
        runtime = ControlRuntime(settings, scene)
    except ValueError as exc:  # a fallback region the scene does not have
        raise CliError(str(exc)) from None
    app = create_app(settings, runtime, bus_factory=lambda: Bus.open(settings, SERVICE))
    serve(app, settings)
    return 0


def serve_sim(overrides: dict[str, Any], scenario: str | None = None) -> int:
    from services.sim.api import create_app
    from services.sim.service import SERVICE
    from services.sim.settings import SimSettings
    from shared.bus import Bus
    from shared.serving import serve

    if scenario is not None:
        overrides = {**overrides, "scenario": scenario}
    settings = _exposed(SimSettings(**overrides))
    scene = control_scenario(settings.scenario, flag=scenario is not None)
    try:
        app = create_app(settings, scene, bus_factory=lambda: Bus.open(settings, SERVICE))
    except ValueError as exc:
        raise CliError(str(exc)) from None
    serve(app, settings)
    return 0


def serve_ros2(overrides: dict[str, Any]) -> int:
    from services.control.settings import ControlSettings
    from services.ros2.api import create_app
    from services.ros2.bridge import SERVICE
    from services.ros2.settings import Ros2Settings
    from shared.bus import Bus
    from shared.serving import serve

    settings = _exposed(Ros2Settings(**overrides))
    # its states must be in control's frame, as this environment says it (compose: set
    # AESOP_CONTROL_VEHICLE__FRAME alike for both), or control refuses every one
    config = ros2_config(settings.config, frame=ControlSettings().vehicle.frame)
    serve(create_app(settings, config, bus_factory=lambda: Bus.open(settings, SERVICE)),
          settings)
    return 0


def serve_dashboard(overrides: dict[str, Any]) -> int:
    from services.dashboard.api import create_app
    from services.dashboard.service import SERVICE
    from services.dashboard.settings import DashboardSettings
    from shared.bus import Bus
    from shared.serving import serve

    settings = _exposed(DashboardSettings(**overrides))
    serve(create_app(settings, bus_factory=lambda: Bus.open(settings, SERVICE)), settings)
    return 0


def _exposed(settings: ExposedSettings) -> ExposedSettings:
    """``settings``, unless they would listen off loopback without a token (a usage error
    naming the setting)."""
    try:
        settings.check_exposure()
    except ValueError as exc:
        raise CliError(str(exc)) from None
    return settings
