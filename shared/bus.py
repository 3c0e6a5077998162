"""The one Zenoh <-> asyncio bridge: drop-oldest subscriptions, latest values, queries, liveliness.

Zenoh runs callbacks on its own threads. Here a callback only decodes the
sample and hands it on: to an asyncio loop with ``call_soon_threadsafe`` into
a bounded drop-oldest queue (``Subscription``), or into a lock-guarded slot
that keeps the newest message (``Latest``, for a fixed-rate control loop).
It never calls Zenoh, never blocks and never raises.

    with Bus.open(settings, "embedding") as bus:
        async for got in bus.subscribe(topics.observation("*"), Observation):
            bus.publish(topics.anomaly(got.message.robot), verdict)
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, Protocol, Self, TypeVar

import zenoh

from shared import topics
from shared.messages import Message
from shared.settings import BusSettings

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)
T = TypeVar("T")
_C = TypeVar("_C", bound="_Closeable")

HEALTH_ALL = f"{topics.PREFIX}/health/*"
_ERROR_LOG_INTERVAL_S = 10.0
# how a session retries a lost router: at once, then backing off to once a second
RECONNECT = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}


def zenoh_config(settings: BusSettings) -> zenoh.Config:
    """A Zenoh config: the JSON5 file if any (``ValueError`` naming a file it cannot read,
    as for the password and TLS files), then mode, endpoints, multicast, the
    reconnection backoff, the TLS files and the user/password from settings.

    With a file, only settings given explicitly (init or ``AESOP_*``) override it;
    without one, all apply (multicast scouting off by default, and a peer with no
    listen endpoint listens on a random loopback port, not on every interface).
    """
    if settings.zenoh_config is not None:
        # zenoh's own error for a missing file names no file; and a caller that cannot
        # open a session blames the router's user and password
        try:
            with open(settings.zenoh_config, "rb"):
                pass
        except OSError as exc:
            raise ValueError(f"AESOP_ZENOH_CONFIG: cannot read {settings.zenoh_config}: "
                             f"{exc.strerror}") from None
        conf = zenoh.Config.from_file(settings.zenoh_config)
        given = settings.model_fields_set
    else:
        conf = zenoh.Config()
        given = {"zenoh_mode", "zenoh_multicast"}
    if settings.zenoh_id is not None:
        conf.insert_json5("id", json.dumps(settings.zenoh_id))
    if "zenoh_mode" in given:
        conf.insert_json5("mode", json.dumps(settings.zenoh_mode))
    listen = settings.zenoh_listen
    if not listen and settings.zenoh_config is None and settings.zenoh_mode == "peer":
        listen = ["tcp/127.0.0.1:0"]  # zenoh's own default listens on every interface
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if settings.zenoh_connect:
        conf.insert_json5("connect/endpoints", json.dumps(settings.zenoh_connect))
    if "zenoh_multicast" in given:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.zenoh_multicast))
    if settings.zenoh_connect:  # back within a second of the router's return
        conf.insert_json5("connect/retry", json.dumps(RECONNECT))
    tls = settings.zenoh_tls()
    if tls is not None:
        for key, value in tls.items():
            conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    secret = settings.zenoh_secret()
    if settings.zenoh_user is not None and secret is not None:
        conf.insert_json5("transport/auth/usrpwd", json.dumps(
            {"user": settings.zenoh_user, "password": secret}))
    return conf


@dataclass(frozen=True, slots=True)
class Received(Generic[T]):
    """A decoded message, the concrete key it came on, and ``time.monotonic()`` at arrival."""

    key: str
    message: T
    received_at: float


@dataclass(frozen=True, slots=True)
class HealthChange:
    """A service's liveliness token appeared (``alive``) or vanished."""

    service: str
    alive: bool
    received_at: float


class _Closeable(Protocol):
    def close(self) -> None: ...


class _Decoder(Generic[M]):
    """Sample -> ``Received[M]`` on the Zenoh thread; counts and rate-limits decode errors
    (``on_error`` is told of each, e.g. to count it in a service's metrics)."""

    def __init__(self, key_expr: str, model: type[M],
                 on_error: Callable[[], None] | None = None,
                 admit: Callable[[str], bool] | None = None) -> None:
        self.key_expr = key_expr
        self.model = model
        self.on_error = on_error
        self.admit = admit
        self.received = 0
        self.decode_errors = 0
        self._lock = threading.Lock()
        self._last_log: float | None = None
        self._unlogged = 0

    def __call__(self, sample: zenoh.Sample) -> Received[M] | None:
        if sample.kind != zenoh.SampleKind.PUT:
            return None
        received_at = time.monotonic()
        key = str(sample.key_expr)
        if self.admit is not None and not self.admit(key):
            return None  # refused before it costs a decode (the caller counted it)
        try:
            message = self.model.decode(sample.payload.to_bytes())
        except Exception as exc:  # a bad payload must never reach the loop
            self._count_error(key, exc)
            return None
        with self._lock:
            self.received += 1
        return Received(key, message, received_at)

    def _count_error(self, key: str, exc: Exception) -> None:
        if self.on_error is not None:
            try:
                self.on_error()
            except Exception:  # a callback must never break the Zenoh thread
                log.exception("on_error of %s failed", self.key_expr)
        now = time.monotonic()
        with self._lock:
            self.decode_errors += 1
            self._unlogged += 1
            if self._last_log is not None and now - self._last_log < _ERROR_LOG_INTERVAL_S:
                return
            self._last_log, count, self._unlogged = now, self._unlogged, 0
        log.warning(
            "dropped %d undecodable %s sample(s) on %s (latest on %s: %s)",
            count,
            self.model.__name__,
            self.key_expr,
            key,
            _first_line(exc),
        )


def _first_line(exc: Exception) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


class _LoopQueue(Generic[T]):
    """A bounded drop-oldest queue fed from any thread, read by one asyncio loop."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be >= 1")
        try:
            self._loop = asyncio.get_running_loop()
        except RuntimeError:
            raise RuntimeError(
                "create subscriptions inside a running asyncio loop (threads: Bus.latest)"
            ) from None
        self._items: deque[T] = deque()
        self._maxsize = maxsize
        self._ready = asyncio.Event()
        self._closed = False
        self.dropped = 0

    @property
    def closed(self) -> bool:
        return self._closed

    def qsize(self) -> int:
        return len(self._items)

    def put_threadsafe(self, item: T) -> None:
        """From any thread; a closed loop or queue silently drops the item."""
        if self._closed:
            return
        # A closed loop raises RuntimeError: nobody is listening any more.
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(self._put, item)

    def _put(self, item: T) -> None:
        if self._closed:
            return
        if len(self._items) >= self._maxsize:
            self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self._ready.set()

    async def get(self) -> T:
        """The oldest item; ``StopAsyncIteration`` once closed."""
        while True:
            if self._closed:
                raise StopAsyncIteration
            if self._items:
                return self._items.popleft()
            self._ready.clear()
            await self._ready.wait()

    def close(self) -> None:
        """From any thread: end every pending and future ``get``."""
        self._closed = True
        try:
            on_loop = asyncio.get_running_loop() is self._loop
        except RuntimeError:
            on_loop = False
        if on_loop:
            self._wake()
            return
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        self._items.clear()
        self._ready.set()


class _Declared:
    """A declared Zenoh subscriber: ``close()`` (or ``with``) undeclares it, once."""

    _undeclare: Callable[[], None]

    def close(self) -> None:
        self._undeclare()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Stream(_Declared, Generic[T]):
    """A declared subscriber read as an async iterator from its drop-oldest queue."""

    _queue: _LoopQueue[T]

    @property
    def dropped(self) -> int:
        """Items discarded because the queue was full (drop-oldest)."""
        return self._queue.dropped

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> T:
        return await self._queue.get()

    def close(self) -> None:
        """Undeclare the subscriber and end the iteration; idempotent."""
        self._queue.close()
        super().close()


class _Decoding(Generic[M]):
    """What both kinds of subscriber say about their samples (via their ``_Decoder``)."""

    _decoder: _Decoder[M]

    @property
    def key_expr(self) -> str:
        return self._decoder.key_expr

    @property
    def received(self) -> int:
        """Samples decoded so far (including any later dropped)."""
        return self._decoder.received

    @property
    def decode_errors(self) -> int:
        return self._decoder.decode_errors


class Subscription(_Stream[Received[M]], _Decoding[M]):
    """Typed samples on ``key_expr`` as an async iterator of ``Received[M]``.

    Create it inside a running loop (``Bus.subscribe``). When the consumer is
    slow the oldest queued message is discarded and counted in ``dropped``.
    """

    def __init__(
        self, session: zenoh.Session, key_expr: str, model: type[M], *, maxsize: int = 64,
        on_error: Callable[[], None] | None = None, admit: Callable[[str], bool] | None = None,
    ) -> None:
        self._queue: _LoopQueue[Received[M]] = _LoopQueue(maxsize)
        self._decoder = _Decoder(key_expr, model, on_error, admit)
        self._subscriber = session.declare_subscriber(key_expr, self._on_sample)
        self._undeclare = _once(self._subscriber.undeclare)

    @property
    def closed(self) -> bool:
        return self._queue.closed

    def qsize(self) -> int:
        return self._queue.qsize()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        got = self._decoder(sample)
        if got is not None:
            self._queue.put_threadsafe(got)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


class Latest(_Declared, _Decoding[M]):
    """The newest decoded message on ``key_expr``; thread-safe, for fixed-rate loops.
    ``on_update`` (quick, never blocking) is called on its thread after each one taken, to
    wake a loop that waits for it.

    Samples wait in a one-slot ring (Zenoh's :class:`~zenoh.handlers.RingChannel`, no lock
    of the interpreter needed), which one thread of its own takes from: a process too busy
    to take each in time (its interpreter's lock held by other threads) skips to the newest
    instead of working through a backlog in order. With a callback per sample, control
    beside two CPU hogs took its vehicle states in up to 1.7 s late (issue 46)."""

    def __init__(self, session: zenoh.Session, key_expr: str, model: type[M],
                 on_update: Callable[[], None] | None = None) -> None:
        self._decoder = _Decoder(key_expr, model)
        self._lock = threading.Lock()
        self._latest: Received[M] | None = None
        self._on_update = on_update
        self._subscriber = session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(1))
        self._undeclare = _once(self._subscriber.undeclare)
        threading.Thread(target=self._drain, name=f"latest {key_expr}", daemon=True).start()

    def _drain(self) -> None:
        handler = self._subscriber.handler
        while True:
            try:
                sample = handler.recv()  # waits without the interpreter's lock
            except zenoh.ZError:  # undeclared: the ring is closed
                return
            try:
                self._on_sample(sample)
            except Exception:  # an on_update that raised: logged, the next one is taken
                log.exception("%s: taking a sample failed", self._decoder.key_expr)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        got = self._decoder(sample)
        if got is not None:
            with self._lock:
                self._latest = got
            if self._on_update is not None:
                self._on_update()

    def get(self) -> Received[M] | None:
        with self._lock:
            return self._latest

    def age(self, now: float | None = None) -> float | None:
        """Seconds since the newest message arrived (``time.monotonic()`` clock), None if none."""
        got = self.get()
        if got is None:
            return None
        return (time.monotonic() if now is None else now) - got.received_at


class Each(_Declared, _Decoding[M]):
    """Every decoded message on ``key_expr`` handed to ``handler`` on the Zenoh thread, no
    loop and no queue: for a process whose work per message is short and must not wait
    behind a loop (the reasoner's deadline keeper). ``handler`` must be quick, must not
    block and must not call Zenoh back synchronously from a query; one that raises is
    logged, never the Zenoh thread's problem."""

    def __init__(self, session: zenoh.Session, key_expr: str, model: type[M],
                 handler: Callable[[Received[M]], None],
                 on_error: Callable[[], None] | None = None) -> None:
        self._decoder = _Decoder(key_expr, model, on_error)
        self._handler = handler
        self._subscriber = session.declare_subscriber(key_expr, self._on_sample)
        self._undeclare = _once(self._subscriber.undeclare)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        got = self._decoder(sample)
        if got is None:
            return
        try:
            self._handler(got)
        except Exception:  # a callback must never break the Zenoh thread
            log.exception("handling a sample on %s failed", self._decoder.key_expr)


class Answering(_Declared):
    """A queryable on ``key``: each query is answered with ``reply()``, on a Zenoh thread
    (``reply`` must be quick and must not block; one that raises answers nothing)."""

    def __init__(self, session: zenoh.Session, key: str, reply: Callable[[], Message]) -> None:
        self.key = key
        self._reply = reply
        self._queryable = session.declare_queryable(key, self._on_query)
        self._undeclare = _once(self._queryable.undeclare)

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(self.key, self._reply().encode())
        except Exception:  # a callback must never break the Zenoh thread
            log.exception("answering a query on %s failed", self.key)


class Serving(_Declared, Generic[M]):
    """A queryable on ``key`` whose queries carry a ``model`` message: each is answered
    with ``handle(message)`` (nothing when it returns None, or when the query's payload
    does not decode: logged), on a Zenoh thread (``handle`` must be quick)."""

    def __init__(self, session: zenoh.Session, key: str, model: type[M],
                 handle: Callable[[M], Message | None]) -> None:
        self.key, self._model, self._handle = key, model, handle
        self._queryable = session.declare_queryable(key, self._on_query)
        self._undeclare = _once(self._queryable.undeclare)

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        try:
            message = self._model.decode(b"" if payload is None else payload.to_bytes())
        except ValueError as exc:
            log.warning("a query on %s was not a %s: %s", self.key, self._model.__name__,
                        _first_line(exc))
            return
        try:
            answer = self._handle(message)
            if answer is not None:
                query.reply(self.key, answer.encode())
        except Exception:  # a callback must never break the Zenoh thread
            log.exception("answering a query on %s failed", self.key)


class LivelinessWatch(_Stream[HealthChange]):
    """Async iterator of ``HealthChange``s of services under a health prefix."""

    def __init__(
        self, session: zenoh.Session, key_expr: str, *, history: bool = True, maxsize: int = 256
    ) -> None:
        self._queue: _LoopQueue[HealthChange] = _LoopQueue(maxsize)
        self._subscriber = session.liveliness().declare_subscriber(
            key_expr, self._on_sample, history=history
        )
        self._undeclare = _once(self._subscriber.undeclare)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        service = _service_of(str(sample.key_expr))
        self._queue.put_threadsafe(HealthChange(service, alive, time.monotonic()))


def _service_of(key: str) -> str:
    return key.rsplit("/", 1)[-1]


def _once(undeclare: Callable[[], object]) -> Callable[[], None]:
    """Make a Zenoh ``undeclare`` idempotent and quiet (it raises when repeated or closed)."""
    done = threading.Event()

    def run() -> None:
        if done.is_set():
            return
        done.set()
        try:
            undeclare()
        except zenoh.ZError as exc:
            log.debug("undeclare: %s", exc)

    return run


class Bus:
    """A Zenoh session for one service: typed pub/sub plus its liveliness token."""

    def __init__(self, session: zenoh.Session, service: str, *, alive: bool = True) -> None:
        self._session = session
        self.service = service
        self._lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._children: weakref.WeakSet[_Closeable] = weakref.WeakSet()
        self._token: zenoh.LivelinessToken | None = None
        self._closed = False
        if alive:
            self.announce()

    @classmethod
    def open(cls, settings: BusSettings, service: str, *, alive: bool = True) -> Self:
        """Open a session and declare the liveliness token ``aesop/health/{service}``
        (``alive=False``: later, by :meth:`announce`)."""
        topics.health(service)  # validate before opening anything
        session = zenoh.open(zenoh_config(settings))
        try:
            return cls(session, service, alive=alive)
        except BaseException:
            # zenoh's stub leaves Session.close unannotated
            session.close()  # type: ignore[no-untyped-call]
            raise

    def announce(self) -> None:
        """Declare the liveliness token ``aesop/health/{service}`` (once). Declarations
        travel in order on a link: a peer that sees the token has seen every subscriber
        declared before it, so a service that announces after subscribing is heard as
        soon as it is seen alive."""
        with self._lock:
            if self._token is None and not self._closed:
                self._token = self._session.liveliness().declare_token(
                    topics.health(self.service))

    @property
    def session(self) -> zenoh.Session:
        """The raw Zenoh session, for what the bus does not wrap."""
        return self._session

    @property
    def closed(self) -> bool:
        return self._closed

    def publish(self, key: str, msg: Message) -> None:
        """Put ``msg`` as JSON on the concrete ``key`` (a publisher is declared once per key).

        Thread-safe; raises ``RuntimeError`` once the bus is closed.
        """
        with self._lock:
            if self._closed:
                raise RuntimeError("bus is closed")
            publisher = self._publishers.get(key)
            if publisher is None:
                publisher = self._session.declare_publisher(
                    key, encoding=zenoh.Encoding.APPLICATION_JSON
                )
                self._publishers[key] = publisher
        publisher.put(msg.encode())

    def subscribe(self, key_expr: str, model: type[M], *, maxsize: int = 64,
                  on_error: Callable[[], None] | None = None,
                  admit: Callable[[str], bool] | None = None) -> Subscription[M]:
        """An async iterator of ``model`` messages; call from inside the running loop.
        ``on_error`` is called (on a Zenoh thread) for each sample that does not decode;
        ``admit(key)`` (on a Zenoh thread, quick) is asked first, and a sample it refuses
        is neither decoded nor queued."""
        return self._adopt(Subscription(self._open_session(), key_expr, model, maxsize=maxsize,
                                        on_error=on_error, admit=admit))

    def latest(self, key_expr: str, model: type[M],
               on_update: Callable[[], None] | None = None) -> Latest[M]:
        """A slot holding the newest ``model`` message on ``key_expr``; no loop needed
        (``on_update``: called on the Zenoh thread after each message)."""
        return self._adopt(Latest(self._open_session(), key_expr, model, on_update))

    def watch_alive(self, prefix: str = HEALTH_ALL, *, history: bool = True) -> LivelinessWatch:
        """An async iterator of services appearing and vanishing; call inside the loop."""
        return self._adopt(LivelinessWatch(self._open_session(), prefix, history=history))

    def each(self, key_expr: str, model: type[M], handler: Callable[[Received[M]], None], *,
             on_error: Callable[[], None] | None = None) -> Each[M]:
        """Hand every ``model`` message to ``handler`` on the Zenoh thread (see :class:`Each`)."""
        return self._adopt(Each(self._open_session(), key_expr, model, handler, on_error))

    def answer(self, key: str, reply: Callable[[], Message]) -> Answering:
        """Answer every query on the concrete ``key`` with ``reply()`` (a queryable)."""
        return self._adopt(Answering(self._open_session(), key, reply))

    def serve(self, key: str, model: type[M], handle: Callable[[M], Message | None]
              ) -> Serving[M]:
        """Answer every query on the concrete ``key`` that carries a ``model`` message with
        ``handle(message)`` (see :class:`Serving`)."""
        return self._adopt(Serving(self._open_session(), key, model, handle))

    def ask(self, key: str, model: type[M], *, timeout: float = 1.0,
            payload: Message | None = None) -> list[Received[M]]:
        """Query ``key`` (carrying ``payload``, if any) and decode the answers as ``model``
        (one that does not decode is left out); blocks until the query completes, at most
        ``timeout`` s. Each answer's ``received_at`` is its arrival
        (``time.monotonic()``)."""
        decoder = _Decoder(key, model)
        out: list[Received[M]] = []
        body = None if payload is None else payload.encode()
        for reply in self._open_session().get(key, timeout=timeout, payload=body):
            sample = reply.ok
            got = None if sample is None else decoder(sample)
            if got is not None:
                out.append(got)
        return out

    def alive(self, prefix: str = HEALTH_ALL, *, timeout: float = 2.0) -> set[str]:
        """Names of the services whose liveliness tokens under ``prefix`` are alive now.

        Blocks until the query completes (at most ``timeout`` s); from async code
        prefer ``await asyncio.to_thread(bus.alive)``. Ask from a session that does not
        also watch liveliness (:meth:`watch_alive`): under load Zenoh 1.10.2 can answer
        such a session's query with nothing at once (41 of 150 tries with three busy
        processes on two cores; none of 150 from a session without the watch).
        """
        alive: set[str] = set()
        for reply in self._open_session().liveliness().get(prefix, timeout=timeout):
            sample = reply.ok
            if sample is not None:
                alive.add(_service_of(str(sample.key_expr)))
        return alive

    def close(self) -> None:
        """Undeclare everything and close the session; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            publishers, self._publishers = list(self._publishers.values()), {}
            token, self._token = self._token, None
        for child in list(self._children):
            child.close()
        for publisher in publishers:
            _once(publisher.undeclare)()
        if token is not None:
            _once(token.undeclare)()
        # zenoh's stub leaves Session.close unannotated
        self._session.close()  # type: ignore[no-untyped-call]

    def _open_session(self) -> zenoh.Session:
        if self._closed:
            raise RuntimeError("bus is closed")
        return self._session

    def _adopt(self, child: _C) -> _C:
        self._children.add(child)
        return child

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()
