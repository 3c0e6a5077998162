"""A TCP fault proxy: delay, jitter, stalls and cuts on a real link between two hosts.

The robot's Zenoh router reaches the server's router through it. These kernels have no
``tc netem``, so this is how the tests and ``aesop bench link`` make a real TCP link behave
as a poor Wi-Fi link does to the two endpoints:

- **delay / jitter** (:class:`Impairment`): a chunk read from one side at ``t`` is written
  to the other at ``max(previous release that way, t + delay + uniform(±jitter))``. TCP
  reorders nothing, so jitter only bunches chunks; each direction of each connection is
  its own ordered pipe, and RTT grows by twice the one-way delay.
- **stall** (a one-second Wi-Fi hiccup): nothing is read from or written to any socket, so
  the endpoints' kernel buffers fill and hold their senders back as when ACKs stop; what is
  held flows in order afterwards, still delayed.
- **cut** (the link goes dark): a blackhole, not a reset. Nothing is read, written or
  signalled (no FIN, no RST) until :meth:`FaultProxy.heal`. New connections are accepted
  but not connected upstream until then. An endpoint that closes meanwhile (its Zenoh
  lease expired) is seen only at heal, since its socket is not read: its last bytes and its
  FIN then reach the other side, and what was held for it is lost with it.

One asyncio loop in a daemon thread serves every connection with protocols (no thread or
task per chunk): a pipe is a deque of ``(release, bytes)`` and one writer task, and a
pipe holding more than :data:`HIGH_WATER` stops reading its source, so a slow or stalled
side pushes back on its sender as a real link would. Bytes the proxy already handed to the
kernel before a stall or cut still reach the peer: they were already across the air.

:func:`measure_rtt` puts the proxy in front of an echo server of its own, so a benchmark
can report the link's round trip independently of Zenoh.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import socket
import threading
import time
from collections import deque
from collections.abc import Coroutine
from dataclasses import dataclass
from types import TracebackType
from typing import Any

HIGH_WATER = 4 << 20  # bytes one direction holds before the proxy stops reading its source
LOW_WATER = 1 << 20  # ... and resumes
BATCH = 256 << 10  # most bytes one write joins: released chunks go out together
APPLY_TIMEOUT_S = 5.0  # how long stall/cut/heal wait for the loop to have applied them
JOIN_TIMEOUT_S = 10.0
SHUTDOWN_ROUNDS = 50  # loop iterations close() waits for the sockets it aborted to close


@dataclass(frozen=True)
class Impairment:
    """What the link does now to each chunk, in each direction separately."""

    delay_ms: float = 0.0  # one way: a round trip adds twice this
    jitter_ms: float = 0.0  # a chunk's delay is delay_ms + uniform(-jitter, +jitter), >= 0

    def __post_init__(self) -> None:
        if self.delay_ms < 0 or self.jitter_ms < 0:
            raise ValueError(f"delay and jitter are non-negative: {self}")


class _Pipe:
    """One direction of one connection: chunks read from ``src`` wait here, in order, until
    their release and an open link, then one task writes them to ``dst``."""

    def __init__(self, link: _Link, src: _End, dst: _End, counter: str) -> None:
        self.link = link
        self.proxy = link.proxy
        self.src = src
        self.dst = dst
        self.counter = counter
        self.items: deque[tuple[float, bytes | None]] = deque()  # None: the source's EOF
        self.last_release = 0.0
        self.held = 0
        self.backlogged = False
        self.ended = False  # the source's EOF is queued
        self.done = False  # EOF delivered, or the destination is gone
        self.wake = asyncio.Event()
        self.task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self.task = self.proxy.spawn(self.run())

    def _release(self) -> float:
        self.last_release = max(self.last_release, time.monotonic() + self.proxy.delay_s())
        return self.last_release

    def push(self, data: bytes) -> None:
        if self.done or self.ended:
            self.proxy.count("dropped_bytes", len(data))
            return
        self.items.append((self._release(), data))
        self.held += len(data)
        self.proxy.count("held_bytes", len(data))
        self.wake.set()
        if self.held >= HIGH_WATER and not self.backlogged:
            self.backlogged = True
            self.src.sync_reading()

    def finish(self) -> None:
        """The source sent its FIN or went away: pass that on after what it sent."""
        if self.ended or self.done:
            return
        self.ended = True
        self.items.append((self._release(), None))
        self.wake.set()

    def kill(self) -> None:
        """The destination is gone: what is held for it is lost."""
        self.proxy.count("held_bytes", -self.held)
        self.proxy.count("dropped_bytes", self.held)
        self.items.clear()
        self.held = 0
        self.done = True
        if self.task is not None and self.task is not asyncio.current_task():
            self.task.cancel()

    async def run(self) -> None:
        try:
            while not self.done:
                # every await may change the state, so each one starts the checks over
                if not self.items:
                    self.wake.clear()
                    await self.wake.wait()
                    continue
                wait = self.items[0][0] - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
                elif not self.proxy.flowing:
                    await self.proxy.gate.wait()
                elif not self.dst.writable.is_set():
                    await self.dst.writable.wait()
                else:
                    self._flush()
        except Exception:
            self.link.abort()
            raise

    def _flush(self) -> None:
        transport = self.dst.transport
        if transport is None or self.dst.lost or transport.is_closing():
            self.kill()
            self.link.check_done()
            return
        now = time.monotonic()
        chunks: list[bytes] = []
        size = 0
        eof = False
        while self.items and self.items[0][0] <= now and size < BATCH:
            data = self.items.popleft()[1]
            if data is None:
                eof = True
                break
            chunks.append(data)
            size += len(data)
        if chunks:
            transport.write(b"".join(chunks))
            self.held -= size
            self.proxy.count("held_bytes", -size)
            self.proxy.count(self.counter, size)
            if self.backlogged and self.held <= LOW_WATER:
                self.backlogged = False
                self.src.sync_reading()
        if eof:
            try:
                transport.write_eof()
            except OSError:  # the destination was reset since; the link ends with it
                transport.abort()
            self.done = True
            self.link.check_done()


class _End(asyncio.Protocol):
    """One endpoint's socket as the proxy holds it: what it reads goes into ``out``; what
    ``into`` releases is written to it."""

    def __init__(self, link: _Link, *, upstream: bool) -> None:
        self.link = link
        self.upstream = upstream
        self.transport: asyncio.Transport | None = None
        self.out: _Pipe | None = None
        self.into: _Pipe | None = None
        self.writable = asyncio.Event()
        self.writable.set()
        self.eof = False
        self.lost = False
        link.proxy.ends.add(self)  # its transport exists already; connection_made comes later

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.link.made(self)

    def data_received(self, data: bytes) -> None:
        if self.out is not None:
            self.out.push(data)
        else:  # reading is paused until the link is wired; kept for safety's sake
            self.link.proxy.count("dropped_bytes", len(data))

    def eof_received(self) -> bool:
        self.eof = True
        if self.out is not None:
            self.out.finish()
        self.sync_reading()
        return True  # a half-close: the other way may still carry data

    def connection_lost(self, exc: Exception | None) -> None:
        self.link.proxy.ends.discard(self)
        self.lost = True
        self.writable.set()
        self.link.lost(self)

    def pause_writing(self) -> None:
        self.writable.clear()

    def resume_writing(self) -> None:
        self.writable.set()

    def sync_reading(self) -> None:
        """Read only while the link is open, both ends are there and ``out`` has room: the
        only way this proxy leaves bytes in the kernel so the sender feels it."""
        transport = self.transport
        if transport is None or transport.is_closing():
            return
        out = self.out
        if (self.link.proxy.flowing and out is not None and not out.backlogged
                and not self.eof and not self.lost):
            transport.resume_reading()
        else:
            transport.pause_reading()


class _Link:
    """One proxied connection: the client's end, the upstream end once connected, and a
    pipe each way between them."""

    def __init__(self, proxy: FaultProxy) -> None:
        self.proxy = proxy
        self.client = _End(self, upstream=False)
        self.server: _End | None = None
        self.pipes: tuple[_Pipe, ...] = ()  # (up, down) once the upstream end is made
        self.closed = False

    def made(self, end: _End) -> None:
        if not end.upstream:
            end.sync_reading()  # paused: nothing to write to yet
            self.proxy.accepted(self)
            return
        if self.closed:
            if end.transport is not None:
                end.transport.close()
            return
        self.server = end
        up = _Pipe(self, self.client, end, "bytes_up")
        down = _Pipe(self, end, self.client, "bytes_down")
        self.client.out = end.into = up
        end.out = self.client.into = down
        self.pipes = (up, down)
        for pipe in self.pipes:
            pipe.start()
        self.sync_reading()

    def sync_reading(self) -> None:
        self.client.sync_reading()
        if self.server is not None:
            self.server.sync_reading()

    def lost(self, end: _End) -> None:
        if self.closed:
            return
        if end.out is None or end.into is None:  # gone before the upstream end was made
            self.close()
            return
        end.out.finish()
        end.into.kill()
        self.check_done()

    def check_done(self) -> None:
        if not self.closed and self.pipes and all(pipe.done for pipe in self.pipes):
            self.close()

    def close(self) -> None:
        """Both ways are through: close both sockets once their last bytes are written."""
        self._end(abort=False)

    def abort(self) -> None:
        """The proxy closes: drop what is held and close both sockets now."""
        for pipe in self.pipes:
            if not pipe.done:
                pipe.kill()
        self._end(abort=True)

    def _end(self, *, abort: bool) -> None:
        if self.closed:
            return
        self.closed = True
        for end in (self.client, self.server):
            if end is not None and end.transport is not None:
                if abort:
                    end.transport.abort()
                else:
                    end.transport.close()
        self.proxy.forget(self)


class FaultProxy:
    """Listens on ``listen`` and joins each connection to ``upstream`` through an impaired
    link (see the module's docstring). Every public method is safe from any thread."""

    def __init__(self, listen: tuple[str, int], upstream: tuple[str, int], *,
                 seed: int = 0) -> None:
        self.listen = listen
        self.upstream = upstream
        self._impairment = Impairment()
        self._random = random.Random(seed)
        self._lock = threading.Lock()  # the cut and the stall's end, set by any thread
        self._cut = False
        self._stall_until = 0.0
        self._stats: dict[str, int | bool] = {
            "accepted": 0, "open": 0, "bytes_up": 0, "bytes_down": 0, "held_bytes": 0,
            "dropped_bytes": 0, "upstream_failures": 0, "cuts": 0, "stalls": 0,
            "cut": False, "stalled": False}
        self.gate = asyncio.Event()  # set while bytes may move; touched in the loop only
        self._stop = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._port = 0
        self._error: BaseException | None = None
        self._links: set[_Link] = set()
        self.ends: set[_End] = set()  # every socket not yet closed, to abort at close()
        self._tasks: set[asyncio.Task[None]] = set()
        self._stall_timer: asyncio.TimerHandle | None = None
        self._closed = False

    # -- the caller's side

    def start(self) -> FaultProxy:
        """Run the proxy's loop in a daemon thread; return once it listens."""
        if self._thread is not None:
            raise RuntimeError("the proxy is already started")
        ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(ready,), daemon=True,
                                        name=f"fault-proxy-{self.listen[1]}")
        self._thread.start()
        ready.wait()
        if self._error is not None:
            self._thread.join(JOIN_TIMEOUT_S)
            raise self._error
        return self

    @property
    def port(self) -> int:
        """The port it listens on (the one the system chose for a listen port of 0)."""
        if not self._port:
            raise RuntimeError("the proxy is not started")
        return self._port

    @property
    def running(self) -> bool:
        """Its loop's thread is alive (started, and not yet closed)."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def impairment(self) -> Impairment:
        return self._impairment

    def set(self, impairment: Impairment) -> None:
        """Impair the chunks read from now on; those already held keep their release."""
        self._impairment = impairment

    def stall(self, seconds: float) -> None:
        """Nothing moves for ``seconds`` from now (a stall already on lasts to the later
        end); returns once no byte moves any more."""
        if seconds < 0:
            raise ValueError(f"a stall lasts a non-negative time, not {seconds}")
        with self._lock:
            self._stall_until = max(self._stall_until, time.monotonic() + seconds)
            self._stats["stalls"] += 1
        self._apply()

    def cut(self) -> None:
        """The link goes dark until :meth:`heal`; returns once no byte moves any more."""
        with self._lock:
            if not self._cut:
                self._stats["cuts"] += 1
            self._cut = True
        self._apply()

    def heal(self) -> None:
        """End a cut: what is held flows in order; returns once the loop has applied it."""
        with self._lock:
            self._cut = False
        self._apply()

    @property
    def stats(self) -> dict[str, int | bool]:
        """Connections ``accepted`` and ``open``; ``bytes_up`` (client to upstream) and
        ``bytes_down`` delivered; ``held_bytes`` read and not yet written; ``dropped_bytes``
        (held for an endpoint that went away, or at close); ``upstream_failures``; ``cuts`` and
        ``stalls`` begun; whether it is ``cut`` or ``stalled`` now."""
        return dict(self._stats)

    def close(self) -> None:
        """Stop listening, drop what is held, close every connection, join the thread."""
        if self._closed:
            return
        self._closed = True
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop already ended
            loop.call_soon_threadsafe(self._stop.set)
        if thread is not threading.current_thread():
            thread.join(JOIN_TIMEOUT_S)

    def __enter__(self) -> FaultProxy:
        return self if self._thread is not None else self.start()

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _apply(self) -> None:
        """Have the loop apply the cut and stall state, and wait for it: once ``cut()``
        returns, the bytes a test sends are sure to be held."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or self._closed:
            return
        if thread is threading.current_thread():
            self._refresh()
            return
        done = threading.Event()

        def refresh() -> None:
            try:
                self._refresh()
            finally:
                done.set()

        try:
            loop.call_soon_threadsafe(refresh)
        except RuntimeError:  # the loop already ended
            return
        done.wait(APPLY_TIMEOUT_S)

    # -- the loop's side

    @property
    def flowing(self) -> bool:
        return self.gate.is_set()

    def delay_s(self) -> float:
        impairment = self._impairment
        ms = impairment.delay_ms
        if impairment.jitter_ms:
            ms += self._random.uniform(-impairment.jitter_ms, impairment.jitter_ms)
        return max(ms, 0.0) / 1e3

    def count(self, key: str, n: int) -> None:
        self._stats[key] += n

    def spawn(self, coro: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def accepted(self, link: _Link) -> None:
        self._links.add(link)
        self.count("accepted", 1)
        self.count("open", 1)
        if self._stop.is_set():  # accepted as the proxy closes
            link.abort()
        else:
            self.spawn(self._connect(link))

    def forget(self, link: _Link) -> None:
        if link in self._links:
            self._links.discard(link)
            self.count("open", -1)

    def _run(self, ready: threading.Event) -> None:
        try:
            asyncio.run(self._main(ready))
        except BaseException as exc:  # start() raises it in the caller's thread
            self._error = exc
        finally:
            ready.set()

    async def _main(self, ready: threading.Event) -> None:
        self._loop = asyncio.get_running_loop()
        server = await self._loop.create_server(lambda: _Link(self).client, *self.listen)
        self._port = server.sockets[0].getsockname()[1]
        self._refresh()
        ready.set()
        try:
            await self._stop.wait()
        finally:
            # stop accepting first, and close the listener only once every accept under
            # way is through: Python 3.11 fails a transport it makes for a closed server
            # and leaks its socket
            for sock in server.sockets:
                self._loop.remove_reader(sock.fileno())
            await self._abort_all()
            server.close()

    async def _abort_all(self) -> None:
        """Abort every socket, those accepted a moment ago included: a socket closes in a
        later callback, which must run before the loop ends or its descriptor leaks."""
        for task in list(self._tasks):
            task.cancel()
        for round_ in range(SHUTDOWN_ROUNDS):
            for link in list(self._links):
                link.abort()
            for end in list(self.ends):
                if end.transport is not None:
                    end.transport.abort()
            # an accept already under way makes its socket one or two iterations later
            if round_ >= 3 and not self.ends and not self._tasks:
                return
            await asyncio.sleep(0)

    async def _connect(self, link: _Link) -> None:
        """Connect the accepted client upstream, once the link is open."""
        while not self.flowing:
            await self.gate.wait()
        if link.closed:
            return
        assert self._loop is not None
        try:
            await self._loop.create_connection(lambda: _End(link, upstream=True),
                                               *self.upstream)
        except OSError:
            self.count("upstream_failures", 1)
            link.close()

    def _refresh(self) -> None:
        """Open or close the gate from the cut and the stall, and have every socket read
        only while it is open."""
        assert self._loop is not None
        with self._lock:
            cut, until = self._cut, self._stall_until
        now = time.monotonic()
        stalled = now < until
        if self._stall_timer is not None:
            self._stall_timer.cancel()
            self._stall_timer = None
        if stalled:
            self._stall_timer = self._loop.call_later(until - now, self._refresh)
        self._stats["cut"], self._stats["stalled"] = cut, stalled
        if cut or stalled:
            self.gate.clear()
        else:
            self.gate.set()
        for link in list(self._links):
            link.sync_reading()


class _EchoServer:
    """A blocking echo server on 127.0.0.1 for one connection, in a daemon thread."""

    def __init__(self, timeout_s: float) -> None:
        self._sock = socket.create_server(("127.0.0.1", 0))
        self._sock.settimeout(timeout_s)
        host, port = self._sock.getsockname()[:2]
        self.address: tuple[str, int] = (host, port)
        self._thread = threading.Thread(target=self._serve, daemon=True, name="echo")

    def _serve(self) -> None:
        with contextlib.suppress(OSError):
            conn, _ = self._sock.accept()
            with conn:
                while data := conn.recv(65536):
                    conn.sendall(data)

    def __enter__(self) -> _EchoServer:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes an accept() still waiting
        self._sock.close()
        self._thread.join(1.0)


def _round_trip_ms(sock: socket.socket, message: bytes) -> float:
    start = time.perf_counter()
    sock.sendall(message)
    got = 0
    while got < len(message):
        chunk = sock.recv(len(message) - got)
        if not chunk:
            raise ConnectionError("the echo through the proxy closed")
        got += len(chunk)
    return (time.perf_counter() - start) * 1e3


def measure_rtt(impairment: Impairment, samples: int = 50, *, seed: int = 0,
                size: int = 64, timeout_s: float = 30.0) -> list[float]:
    """``samples`` round trips (ms) of a ``size``-byte message through a :class:`FaultProxy`
    impaired so, to an echo server of its own: the link's RTT, whatever Zenoh adds on top.
    One round trip before them warms the connection (the upstream connect is not one)."""
    message = bytes(i % 256 for i in range(size))
    with _EchoServer(timeout_s) as echo, \
            FaultProxy(("127.0.0.1", 0), echo.address, seed=seed) as proxy:
        proxy.set(impairment)
        with socket.create_connection(("127.0.0.1", proxy.port), timeout=timeout_s) as sock:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            _round_trip_ms(sock, message)
            return [_round_trip_ms(sock, message) for _ in range(samples)]
