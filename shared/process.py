"""Child processes of the stack, and the one way to supervise them.

* :class:`Child` runs one :class:`ChildSpec` in its own process group, forwards
  each line of its output to a :data:`Sink` (``[control] ...`` on a terminal,
  or ``control.log``), answers whether it is ready (``/readyz``, or a TCP accept
  for the Zenoh hub) and passes signals to its whole group.
* :func:`await_ready` waits for several children at once and names the one
  that died or never became ready, with the tail of its output.
* :class:`ServiceProcess` is one ``python -m tools.cli ...`` child with a
  log file, started ready or not at all (the benchmarks and the tests);
  ``aesop up`` and ``aesop demo`` supervise a whole stack with
  :class:`tools.stack.up.Stack`, on the same :class:`Child`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Literal

import httpx

Sink = Callable[[str, str], None]  # (child name, one line of its output)


EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")


def ephemeral_range() -> tuple[int, int]:
    """The ports the kernel hands outgoing connections (Linux's default where unknown)."""
    try:
        low, high = (int(x) for x in EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        return 32768, 60999
    return low, high


def free_port() -> int:
    """A TCP port free on loopback right now (for a child service or a Zenoh endpoint),
    outside the kernel's ephemeral range: outgoing connections take their local ports
    from that range, and one took a port picked there before the child could bind it
    (a test stack's service failed with EADDRINUSE)."""
    low, high = ephemeral_range()
    below, above = range(10_000, low), range(high + 1, 65_536)
    pool = below if len(below) >= len(above) else above
    for _ in range(200):
        port = random.choice(pool)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:  # a crowded machine
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def port_in_use(port: int, host: str = "127.0.0.1") -> bool:
    """Whether a server could not bind ``host:port`` now: something listens there, or holds
    it bound without listening (a connect would miss that one). Tried as the services bind
    (``SO_REUSEADDR``), so a closed connection's ``TIME_WAIT`` does not count; an address
    this machine does not have is not "in use" (the server that binds it says why)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            return exc.errno == errno.EADDRINUSE
    return False


class ServiceFailed(RuntimeError):
    """A child exited or never became ready; the message says which and why."""


@dataclass(frozen=True)
class ChildSpec:
    name: str
    argv: tuple[str, ...]
    port: int
    env: Mapping[str, str]
    ready: Literal["http", "tcp"] = "http"
    host: str = "127.0.0.1"  # where it is ready: the address its port accepts on

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


class Child:
    """One child process in its own process group, its output forwarded line by line to
    ``sink``, or written straight to ``log_path`` (no thread in between: a busy parent
    never slows the child down, and a killed child's last lines are on disk)."""

    def __init__(self, spec: ChildSpec, sink: Sink, *, log_path: Path | None = None) -> None:
        self.spec, self.sink, self.log_path = spec, sink, log_path
        self.proc: subprocess.Popen[bytes] | None = None
        self._pump: threading.Thread | None = None
        self._tail: list[str] = []

    @property
    def tail(self) -> list[str]:
        """The last lines of the child's output."""
        if self.log_path is None:
            return self._tail
        try:
            return self.log_path.read_text(errors="replace").splitlines()[-30:]
        except OSError:
            return []

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def start(self) -> None:
        self._tail = []
        if self.log_path is not None:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.log_path, "ab") as log:
                self.proc = subprocess.Popen(list(self.spec.argv), env=dict(self.spec.env),
                                             stdout=log, stderr=subprocess.STDOUT,
                                             stdin=subprocess.DEVNULL, start_new_session=True)
            return
        self.proc = subprocess.Popen(list(self.spec.argv), env=dict(self.spec.env),
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True)
        self._pump = threading.Thread(target=self._forward, args=(self.proc.stdout,),
                                      name=f"log-{self.name}", daemon=True)
        self._pump.start()

    def _forward(self, stream: IO[bytes]) -> None:
        for raw in stream:
            line = raw.decode(errors="replace").rstrip()
            self._tail = (self._tail + [line])[-30:]
            self.sink(self.name, line)

    def exited(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def is_ready(self) -> bool:
        if self.spec.ready == "tcp":
            family = socket.AF_INET6 if ":" in self.spec.host else socket.AF_INET
            with socket.socket(family, socket.SOCK_STREAM) as sock:
                sock.settimeout(0.5)
                return sock.connect_ex((self.spec.host, self.spec.port)) == 0
        try:
            return httpx.get(f"{self.spec.url}/readyz", timeout=1.0).status_code == 200
        except httpx.TransportError:
            return False

    def signal(self, sig: signal.Signals) -> None:
        """Send ``sig`` to the child's whole process group."""
        if self.proc is None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, sig)

    def wait(self, timeout_s: float) -> bool:
        if self.proc is None:
            return True
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return False
        if self._pump is not None:
            self._pump.join(2.0)
        return True

    def stop(self, grace_s: float = 15.0) -> None:
        """SIGTERM, then SIGKILL what is left after ``grace_s``."""
        if self.exited() is not None or self.proc is None:
            self.wait(5.0)
            return
        self.signal(signal.SIGTERM)
        if not self.wait(grace_s):
            self.sink(self.name, f"did not stop in {grace_s:g} s: killing it")
            self.signal(signal.SIGKILL)
            self.wait(5.0)


def await_ready(children: Sequence[Child], timeout_s: float, *,
                stopping: threading.Event | None = None,
                on_ready: Callable[[Child], None] = lambda _: None) -> None:
    """Return when every child answers ready; :class:`ServiceFailed` naming the child that
    exited (with its last lines) or those still not ready after ``timeout_s``."""
    waiting = list(children)
    deadline = time.monotonic() + timeout_s
    while waiting:
        if stopping is not None and stopping.is_set():
            raise ServiceFailed("interrupted while starting")
        for child in list(waiting):
            status = child.exited()
            if status is not None:
                raise ServiceFailed(f"{child.name} exited with status {status} while "
                                    "starting:\n" + "\n".join(child.tail[-15:]))
            if child.is_ready():
                on_ready(child)
                waiting.remove(child)
        if time.monotonic() > deadline:
            names = ", ".join(c.name for c in waiting)
            tails = "\n".join(f"[{c.name}] {line}" for c in waiting for line in c.tail[-10:])
            raise ServiceFailed(f"not ready after {timeout_s:.0f} s: {names}\n{tails}")
        time.sleep(0.05)


def stderr_sink(width: int = 10) -> Sink:
    lock = threading.Lock()

    def write(name: str, line: str) -> None:
        with lock:
            print(f"[{name}]".ljust(width + 2) + line, file=sys.stderr, flush=True)

    return write


def file_sink(directory: Path) -> Sink:
    """Each child's lines to ``directory/<name>.log``."""
    directory.mkdir(parents=True, exist_ok=True)
    lock = threading.Lock()
    files: dict[str, IO[str]] = {}

    def write(name: str, line: str) -> None:
        with lock:
            if name not in files:
                files[name] = open(directory / f"{name}.log", "a", encoding="utf-8")  # noqa: SIM115
            files[name].write(line + "\n")
            files[name].flush()

    return write


class ServiceProcess:
    """``python -m tools.cli <args>`` with its output in ``log_path``, started ready."""

    def __init__(self, args: Sequence[str], *, port: int, log_path: Path,
                 env: Mapping[str, str] | None = None, ready_timeout_s: float = 120.0,
                 unset: Sequence[str] = ()) -> None:
        self.args = list(args)
        self.port = port
        self.log_path = log_path
        merged = {k: v for k, v in {**os.environ, **(env or {})}.items() if k not in unset}
        self.env = merged
        self.ready_timeout_s = ready_timeout_s
        name = self.args[1] if len(self.args) > 1 and self.args[0] == "serve" else self.args[0]
        self.child = Child(ChildSpec(name, (sys.executable, "-m", "tools.cli", *self.args),
                                     port, merged), lambda *_: None, log_path=log_path)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def proc(self) -> subprocess.Popen[bytes] | None:
        return self.child.proc

    @property
    def pid(self) -> int:
        return self.child.pid

    def start(self) -> ServiceProcess:
        self.child.start()
        try:
            await_ready([self.child], self.ready_timeout_s)
        except ServiceFailed:
            self.stop()
            raise
        return self

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def kill(self) -> None:
        """SIGKILL: no cleanup at all, as in a crash."""
        if self.child.exited() is None:
            self.child.signal(signal.SIGKILL)
            self.child.wait(10.0)

    def stop(self, timeout_s: float = 15.0) -> None:
        """SIGTERM, then SIGKILL if it does not exit in time."""
        self.child.stop(timeout_s)

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


def stop_on(stop: threading.Event, *signals: signal.Signals) -> None:
    """Set ``stop`` on each of ``signals`` (SIGINT and SIGTERM if none are named).

    Python runs a handler on the main thread between two bytecodes, which may be while
    that thread holds ``stop``'s own lock inside ``stop.wait(timeout)``; ``stop.set()``
    there would wait for that lock for ever. The handler sets it from a thread of its own,
    which gets the lock as soon as the main thread lets go."""
    def handler(signum: int, frame: object) -> None:
        threading.Thread(target=stop.set, name="stop-on-signal", daemon=True).start()

    for sig in signals or (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
