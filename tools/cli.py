"""The ``aesop`` command.

Subcommands import their service lazily, so ``aesop --help`` stays fast and a
service never imports another. With ``--json`` a command prints exactly one
JSON object on stdout; progress and logs go to stderr.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import sys
from collections.abc import Mapping

from pydantic import ValidationError

from shared.logs import configure, log_format
from tools import detector, ros2, serve, watch
from tools.bench import cli as bench_cli
from tools.commands import CliError
from tools.demo import cli as demo_cli
from tools.recording import cli as recording_cli
from tools.stack import cli as stack_cli


def main(argv: list[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else argv
    if given[:2] == ["serve", "fake-llm"] and ({"-h", "--help"} & set(given[2:])):
        from tools.fakes.llm import build_parser as fake_llm_parser

        fake_llm_parser().parse_args(["--help"])  # the fake's own flags (exits 0)
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and getattr(args, "service", None) != "fake-llm":
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.extra = extra
    try:
        configure(logging.INFO, log_format())
    except ValueError as exc:
        print(f"aesop: {exc}", file=sys.stderr)
        return 2
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # which build it found
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    if args.command in ("serve", "up", "demo"):
        # before numpy loads (the settings load it): the services' matrices are small, and
        # OpenBLAS's pool of a thread per core spins between calls, which on a shared
        # machine takes the cores the other loops need (three fleet control loops: half a
        # core each with the pool, a fifth without). OPENBLAS_NUM_THREADS given is kept.
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        warn_unknown_settings(os.environ)
    try:
        if getattr(args, "needs_bench_extra", False):
            require_bench_extra()
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"aesop: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:
        print(f"aesop: invalid settings:\n{exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


# read by docker-compose.yml and the image's scripts (deploy/), not by a service
DEPLOY_VARIABLES = frozenset({
    "AESOP_BASE_IMAGE", "AESOP_DEBIAN_MIRROR", "AESOP_DOCKER_ROOT", "AESOP_DOCKER_STATE",
    "AESOP_IMAGE", "AESOP_POSTGRES_IMAGE", "AESOP_SCENARIO", "AESOP_SCENE_FILE",
    "AESOP_SECRETS"})


def warn_unknown_settings(environ: Mapping[str, str]) -> list[str]:
    """Say which ``AESOP_*`` variables no service reads (an old or misspelt name is
    otherwise silently ignored), but for compose's and the image scripts' own; the lines
    said."""
    from pydantic_settings import BaseSettings

    from services.control.settings import ControlSettings
    from services.dashboard.settings import DashboardSettings
    from services.embedding.settings import EmbeddingSettings
    from services.reasoner.settings import ReasonerSettings
    from services.ros2.settings import Ros2Settings
    from services.sim.settings import SimSettings
    from shared.settings import unknown_names
    from tools.fakes.llm import FakeLLMServiceSettings, FakeLLMSettings

    classes: list[type[BaseSettings]] = [EmbeddingSettings, ReasonerSettings, ControlSettings,
                                          DashboardSettings, SimSettings, Ros2Settings,
                                          FakeLLMServiceSettings, FakeLLMSettings]
    lines = [f"aesop: {name} is not a setting of any service" +
             (f" (did you mean {meant}?)" if meant else "")
             for name, meant in unknown_names(environ, classes).items()
             if name not in DEPLOY_VARIABLES]
    for line in lines:  # a log line: one JSON object under AESOP_LOG_FORMAT=json
        logging.getLogger("aesop").warning("%s", line.removeprefix("aesop: "))
    return lines


BENCH_EXTRA = ("matplotlib", "cvxpy", "psutil")  # what `aesop bench` and `aesop demo` add


def require_bench_extra() -> None:
    """The benchmarks and the demo need the ``bench`` extra, which the image leaves out."""
    missing = [name for name in BENCH_EXTRA if importlib.util.find_spec(name) is None]
    if missing:
        raise CliError(f"this command needs the bench extra ({', '.join(missing)} not "
                       "installed): pip install 'aesop-stack[bench]'")


COMMANDS = (serve, detector, bench_cli, watch, recording_cli, stack_cli, demo_cli, ros2)


def package_version() -> str:
    """The installed aesop-stack's version (``unknown`` where only the sources are)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("aesop-stack")
    except PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """Each command module registers its own subcommands and their handlers."""
    parser = argparse.ArgumentParser(prog="aesop", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in COMMANDS:
        module.register(sub)
    return parser


if __name__ == "__main__":
    sys.exit(main())
