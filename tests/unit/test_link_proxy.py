"""The link's fault proxy (tools/link/proxy.py) over real sockets on 127.0.0.1.

Servers of the test's own stand behind it: an echo server, or a plain one whose accepted
sockets the test drives. Time is asserted only as lower bounds (a delayed or stalled byte
arrives no earlier than it may) or very generous upper bounds, so a loaded machine does not
turn the suite red; "nothing arrives" is checked only while the link is certainly dark.
"""

from __future__ import annotations

import contextlib
import queue
import random
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from tools.link.proxy import FaultProxy, Impairment, measure_rtt

WAIT_S = 15.0  # the most any byte that should come may take: generous, never reached
QUIET_S = 0.4  # how long "nothing arrives" is watched while the link is certainly dark
SLACK_MS = 1.0  # the test's and the proxy's clocks are one, but rounding is not


class Upstream:
    """A listening socket: with ``echo`` each connection's bytes come back; without, the
    accepted sockets wait in ``accepted`` for the test to drive."""

    def __init__(self, *, echo: bool) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        host, port = self.sock.getsockname()[:2]
        self.address = (host, port)
        self.echo = echo
        self.accepted: queue.Queue[socket.socket] = queue.Queue()
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            if self.echo:
                threading.Thread(target=self._echo, args=(conn,), daemon=True).start()
            else:
                self.accepted.put(conn)

    @staticmethod
    def _echo(conn: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := conn.recv(65536):
                conn.sendall(data)
            conn.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        for conn in self.conns:
            conn.close()


@pytest.fixture
def echo() -> Iterator[Upstream]:
    server = Upstream(echo=True)
    yield server
    server.close()


@pytest.fixture
def plain() -> Iterator[Upstream]:
    server = Upstream(echo=False)
    yield server
    server.close()


@pytest.fixture
def make_proxy() -> Iterator[Callable[[Upstream], FaultProxy]]:
    proxies: list[FaultProxy] = []

    def make(upstream: Upstream) -> FaultProxy:
        proxy = FaultProxy(("127.0.0.1", 0), upstream.address, seed=7).start()
        proxies.append(proxy)
        return proxy

    yield make
    for proxy in proxies:
        proxy.close()


@pytest.fixture
def connect() -> Iterator[Callable[[FaultProxy], socket.socket]]:
    opened: list[socket.socket] = []

    def dial(proxy: FaultProxy) -> socket.socket:
        sock = socket.create_connection(("127.0.0.1", proxy.port), timeout=WAIT_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        opened.append(sock)
        return sock

    yield dial
    for sock in opened:
        sock.close()


Joined = tuple[FaultProxy, socket.socket, socket.socket]


@pytest.fixture
def joined(plain: Upstream, make_proxy: Callable[[Upstream], FaultProxy],
           connect: Callable[[FaultProxy], socket.socket]) -> Joined:
    """A proxy to a plain upstream, a client through it and the upstream's side of it."""
    proxy = make_proxy(plain)
    client = connect(proxy)
    return proxy, client, plain.accepted.get(timeout=WAIT_S)


def warm(proxy: FaultProxy, client: socket.socket, server: socket.socket) -> None:
    """A first chunk through, and the proxy holding nothing more: it counts a chunk as held
    until just after writing it, so a check of what it holds next could otherwise be met by
    this one before the next is even read."""
    client.sendall(b"warm")
    assert recv_exactly(server, 4) == b"warm"
    assert eventually(lambda: proxy.stats["held_bytes"] == 0)


def recv_exactly(sock: socket.socket, n: int) -> bytes:
    sock.settimeout(WAIT_S)
    parts = bytearray()
    while len(parts) < n:
        chunk = sock.recv(n - len(parts))
        assert chunk, f"EOF after {len(parts)} of {n} bytes"
        parts += chunk
    return bytes(parts)


def recv_to_eof(sock: socket.socket) -> bytes:
    sock.settimeout(WAIT_S)
    parts = bytearray()
    while chunk := sock.recv(1 << 16):
        parts += chunk
    return bytes(parts)


def quiet(sock: socket.socket) -> bool:
    """Nothing, not even an EOF or a reset, arrives for ``QUIET_S``."""
    sock.settimeout(QUIET_S)
    try:
        sock.recv(1, socket.MSG_PEEK)
    except TimeoutError:
        return True
    return False


def send_in_chunks(sock: socket.socket, data: bytes, seed: int) -> None:
    rng = random.Random(seed)
    at = 0
    while at < len(data):
        size = rng.choice((1, rng.randint(1, 100), rng.randint(100, 70_000)))
        sock.sendall(data[at:at + size])
        at += size


def eventually(check: Callable[[], bool]) -> bool:
    deadline = time.monotonic() + WAIT_S
    while not check():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_bytes_pass_unchanged_and_in_order_both_ways_at_once(
        joined: Joined) -> None:
    proxy, client, server = joined
    rng = random.Random(1)
    up, down = rng.randbytes(3 << 20), rng.randbytes(3 << 20)
    got: dict[str, bytes] = {}

    def side(sock: socket.socket, data: bytes, seed: int, name: str) -> None:
        sender = threading.Thread(target=lambda: (send_in_chunks(sock, data, seed),
                                                  sock.shutdown(socket.SHUT_WR)))
        sender.start()
        got[name] = recv_to_eof(sock)
        sender.join(WAIT_S)

    readers = [threading.Thread(target=side, args=(client, up, 2, "client")),
               threading.Thread(target=side, args=(server, down, 3, "server"))]
    for reader in readers:
        reader.start()
    for reader in readers:
        reader.join(2 * WAIT_S)
    assert got["server"] == up  # each half-close reached the other side after its data
    assert got["client"] == down
    server.close()
    client.close()
    assert eventually(lambda: proxy.stats["open"] == 0)
    stats = proxy.stats
    assert (stats["accepted"], stats["bytes_up"], stats["bytes_down"]) == (1, len(up), len(down))
    assert stats["held_bytes"] == 0


def test_delay_holds_each_way_no_less_than_the_delay(
        plain: Upstream, make_proxy: Callable[[Upstream], FaultProxy],
        connect: Callable[[FaultProxy], socket.socket]) -> None:
    proxy = make_proxy(plain)
    proxy.set(Impairment(delay_ms=150))
    client = connect(proxy)
    server = plain.accepted.get(timeout=WAIT_S)
    for _ in range(2):
        sent = time.monotonic()
        client.sendall(b"ping")
        assert recv_exactly(server, 4) == b"ping"
        arrived = time.monotonic()
        server.sendall(b"pong")
        assert recv_exactly(client, 4) == b"pong"
        back = time.monotonic()
        assert (arrived - sent) * 1e3 >= 150 - SLACK_MS
        assert (back - arrived) * 1e3 >= 150 - SLACK_MS


def test_jitter_keeps_order_over_thousands_of_small_chunks(
        echo: Upstream, make_proxy: Callable[[Upstream], FaultProxy],
        connect: Callable[[FaultProxy], socket.socket]) -> None:
    proxy = make_proxy(echo)
    proxy.set(Impairment(delay_ms=5, jitter_ms=5))
    client = connect(proxy)
    n = 4000
    received: list[bytes] = []
    reader = threading.Thread(target=lambda: received.append(recv_exactly(client, 4 * n)))
    reader.start()
    for i in range(n):
        client.sendall(struct.pack("!I", i))
        if i % 8 == 0:
            time.sleep(0.0002)  # separate chunks, so that jitter has something to reorder
    reader.join(2 * WAIT_S)
    assert received, "the echo did not come back"
    assert list(struct.unpack(f"!{n}I", received[0])) == list(range(n))


def test_a_new_impairment_never_lets_chunks_overtake_held_ones(
        joined: Joined) -> None:
    proxy, client, server = joined
    warm(proxy, client, server)
    # long enough that a loaded machine still sees the chunk held before it is due
    proxy.set(Impairment(delay_ms=2000))
    sent = time.monotonic()
    client.sendall(b"slow.")
    assert eventually(lambda: proxy.stats["held_bytes"] == 5)  # read before the delay is lifted
    proxy.set(Impairment())
    client.sendall(b"fast!")
    assert recv_exactly(server, 10) == b"slow.fast!"
    assert (time.monotonic() - sent) * 1e3 >= 2000 - SLACK_MS


def test_a_stall_holds_every_connection_then_all_flows_in_order(
        echo: Upstream, make_proxy: Callable[[Upstream], FaultProxy],
        connect: Callable[[FaultProxy], socket.socket]) -> None:
    proxy = make_proxy(echo)
    old = connect(proxy)
    old.sendall(b"warm")
    assert recv_exactly(old, 4) == b"warm"
    stall_s = 1.2
    start = time.monotonic()
    proxy.stall(stall_s)
    before = proxy.stats
    data = random.Random(4).randbytes(200_000)
    old.sendall(data)
    new = connect(proxy)  # accepted during the stall, served after it
    new.sendall(b"newcomer")
    time.sleep(0.3)
    during = proxy.stats
    if time.monotonic() < start + stall_s:  # certainly still stalled when read
        assert during["stalled"]
        assert during["bytes_up"] == before["bytes_up"]  # nothing written
        assert during["held_bytes"] == 0  # and nothing read: the kernel holds it all
    assert recv_exactly(old, len(data)) == data
    assert recv_exactly(new, 8) == b"newcomer"
    assert time.monotonic() - start >= stall_s
    stats = proxy.stats
    assert (stats["stalls"], stats["stalled"], stats["accepted"]) == (1, False, 2)


def test_a_cut_holds_everything_silently_until_heal(
        joined: Joined) -> None:
    proxy, client, server = joined
    warm(proxy, client, server)
    delay_s = 0.3
    proxy.set(Impairment(delay_ms=delay_s * 1e3))
    sent = time.monotonic()
    client.sendall(b"in flight")  # read before the cut, released during it
    server.sendall(b"in flight too")
    assert eventually(lambda: proxy.stats["held_bytes"] == 22)
    proxy.cut()
    held = time.monotonic() < sent + delay_s  # certainly not released before the cut
    before = proxy.stats
    rng = random.Random(5)
    up, down = rng.randbytes(100_000), rng.randbytes(100_000)
    client.sendall(up)
    server.sendall(down)
    if held:  # its release then falls within the quiet watch, which must see nothing
        assert before["held_bytes"] == 22
        assert quiet(server) and quiet(client)  # no byte, and no FIN or RST either
    else:  # a very slow machine: watch as long for no byte to be written or read
        time.sleep(2 * QUIET_S)
    during = proxy.stats
    assert during["cut"] and during["cuts"] == 1
    assert during["bytes_up"] == before["bytes_up"] and during["bytes_down"] == before["bytes_down"]
    assert during["held_bytes"] == before["held_bytes"]  # nothing more was read
    proxy.heal()
    assert recv_exactly(server, 9 + len(up)) == b"in flight" + up
    assert recv_exactly(client, 13 + len(down)) == b"in flight too" + down
    assert proxy.stats["cut"] is False


def test_a_connection_made_during_a_cut_reaches_upstream_only_at_heal(
        plain: Upstream, make_proxy: Callable[[Upstream], FaultProxy],
        connect: Callable[[FaultProxy], socket.socket]) -> None:
    proxy = make_proxy(plain)
    proxy.cut()
    client = connect(proxy)
    client.sendall(b"syn of sorts")
    with pytest.raises(queue.Empty):
        plain.accepted.get(timeout=QUIET_S)
    assert proxy.stats["accepted"] == 1
    proxy.heal()
    server = plain.accepted.get(timeout=WAIT_S)
    assert recv_exactly(server, 12) == b"syn of sorts"


@pytest.mark.parametrize("closer", ["client", "server"])
def test_an_endpoint_closing_during_a_cut_is_seen_only_at_heal(
        closer: str, joined: Joined) -> None:
    proxy, client, server = joined
    warm(proxy, client, server)
    gone, other = (client, server) if closer == "client" else (server, client)
    proxy.cut()
    gone.sendall(b"last words")
    other.sendall(b"never read")  # held for an endpoint that is going away
    gone.close()
    assert quiet(other)  # neither its last words nor its FIN
    proxy.heal()
    assert recv_to_eof(other) == b"last words"
    other.close()
    assert eventually(lambda: proxy.stats["open"] == 0)
    assert proxy.stats["held_bytes"] == 0


def test_close_with_held_data_returns_promptly(
        echo: Upstream, make_proxy: Callable[[Upstream], FaultProxy],
        connect: Callable[[FaultProxy], socket.socket]) -> None:
    proxy = make_proxy(echo)
    proxy.set(Impairment(delay_ms=60_000))
    client = connect(proxy)
    client.sendall(b"x" * 50_000)
    assert eventually(lambda: proxy.stats["held_bytes"] > 0)
    proxy.stall(60)
    late = connect(proxy)
    late.sendall(b"also held")
    proxy.close()  # it joins its thread: held data due in a minute must not keep it
    assert not proxy.running
    client.settimeout(WAIT_S)
    with contextlib.suppress(ConnectionResetError):
        assert client.recv(1) == b""  # closed, not left hanging
    proxy.close()  # twice is harmless


def test_an_upstream_that_refuses_closes_the_client(
        make_proxy: Callable[[Upstream], FaultProxy],
        connect: Callable[[FaultProxy], socket.socket]) -> None:
    nobody = Upstream(echo=False)
    nobody.close()  # its port now refuses
    proxy = make_proxy(nobody)
    client = connect(proxy)
    client.settimeout(WAIT_S)
    with contextlib.suppress(ConnectionResetError):
        assert client.recv(1) == b""
    assert eventually(lambda: proxy.stats["open"] == 0)
    assert proxy.stats["upstream_failures"] == 1


def test_measure_rtt_includes_the_delay_both_ways() -> None:
    rtts = measure_rtt(Impairment(delay_ms=25), samples=5)
    assert len(rtts) == 5
    assert min(rtts) >= 50 - SLACK_MS
    plain = measure_rtt(Impairment(), samples=20)
    assert len(plain) == 20 and all(rtt > 0 for rtt in plain)


def test_the_proxy_is_a_context_manager_and_rejects_nonsense(echo: Upstream) -> None:
    with pytest.raises(ValueError):
        Impairment(delay_ms=-1)
    with FaultProxy(("127.0.0.1", 0), echo.address) as proxy:
        with pytest.raises(ValueError):
            proxy.stall(-1)
        with socket.create_connection(("127.0.0.1", proxy.port), timeout=WAIT_S) as sock:
            sock.sendall(b"echo")
            assert recv_exactly(sock, 4) == b"echo"
    with pytest.raises(RuntimeError):
        _ = FaultProxy(("127.0.0.1", 0), echo.address).port
