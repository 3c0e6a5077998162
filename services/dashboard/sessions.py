"""The dashboard's browser sessions, behind its cookie (issue 43, finding 8).

A browser opened with ``/?token=`` gets a cookie that lets it read the flight (``/ws``,
``/v1/snapshot``, ``/v1/fleet``) without the token. Browsers do not scope cookies by port,
so every other web app on the same host receives that cookie too. What it holds is
therefore a random session id, not the token nor anything derived from it, and that
session:

- lives on the server only (this process): a restart ends every session;
- expires ``session_s`` after it was opened (the cookie's ``Max-Age`` too);
- ends on ``POST /logout`` (that one) or ``DELETE /v1/sessions`` (all, with the token);
- when it ends, a WebSocket it opened is closed (1008) within ``check_s``;
- is bound to the client address that opened it (so another app on the dashboard's host
  that replays a remote browser's cookie is refused; a browser on the same host as that
  app has the same address, and there a replay works until expiry or logout);
- is named for the dashboard's port (``aesop_dashboard_<port>``, ``__Host-`` over TLS), so
  two dashboards on one host neither share nor overwrite each other's cookie;
- is one of at most ``limits.sessions``, the oldest going first, so logins cannot grow
  memory.

The :class:`Guard` (``shared.http``) stays the one place that decides: :class:`SessionCookies`,
in front of it, turns a live session into the guard's read-only session value
(``shared.http.session_value``, which never leaves the process) and drops any such value a
request brings itself (the cookie dashboards set before, which never expired). The guard
then lets the session read (GET, HEAD, the WebSocket) and nothing else.
"""

from __future__ import annotations

import asyncio
import hashlib
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from pydantic import SecretStr
from starlette.types import ASGIApp, Receive, Scope, Send

from shared.http import SECURE_SESSION_COOKIE, SESSION_COOKIE, session_value

SCOPE_KEY = "aesop.dashboard.session"  # the live session a request read by (ASGI scope)
COOKIE_PREFIX = "aesop_dashboard_"
SECURE_PREFIX = "__Host-"  # Secure, Path=/, no Domain: the browser keeps it to this host


def cookie_name(port: int, *, secure: bool) -> str:
    """The cookie of the dashboard on ``port``: ``aesop_dashboard_8080`` (``__Host-`` over
    TLS)."""
    return f"{SECURE_PREFIX if secure else ''}{COOKIE_PREFIX}{port}"


def _key(session: str) -> bytes:
    """What the store keeps of a session id: its hash (a lookup of a client's value is then
    no comparison of secrets)."""
    return hashlib.sha256(session.encode("utf-8", "replace")).digest()


@dataclass(frozen=True, slots=True)
class _Session:
    expires: float  # on the store's clock
    client: str  # the address that opened it


class Sessions:
    """The live sessions: at most ``cap``, each ``lifetime_s`` long on ``clock``
    (monotonic; a test passes its own). Kept in the order opened, which is also the order
    they expire in. An open WebSocket looks at its session every ``check_s`` (and at its
    expiry)."""

    def __init__(self, lifetime_s: float, cap: int,
                 clock: Callable[[], float] = time.monotonic, check_s: float = 1.0) -> None:
        self.lifetime_s, self.cap, self.clock, self.check_s = lifetime_s, cap, clock, check_s
        self._live: OrderedDict[bytes, _Session] = OrderedDict()

    def __len__(self) -> int:
        return len(self._live)

    def open(self, client: str) -> str:
        """A new session for ``client``: its id (32 random bytes, URL-safe)."""
        self._drop_expired()
        while len(self._live) >= self.cap:
            self._live.popitem(last=False)  # the oldest
        session = secrets.token_urlsafe(32)
        self._live[_key(session)] = _Session(self.clock() + self.lifetime_s, client)
        return session

    def valid(self, session: str, client: str) -> bool:
        """Whether ``session`` is live and was opened by ``client``."""
        key = _key(session)
        found = self._live.get(key)
        if found is None:
            return False
        if self.clock() >= found.expires:
            del self._live[key]
            return False
        return found.client == client

    async def until_ended(self, session: str, client: str) -> None:
        """Return once ``session`` is no longer live for ``client`` (expired, logged out,
        revoked, evicted)."""
        while self.valid(session, client):
            left = self._live[_key(session)].expires - self.clock()
            await asyncio.sleep(max(0.0, min(left, self.check_s)))

    def close(self, session: str) -> bool:
        """End ``session``; whether it was live."""
        return self._live.pop(_key(session), None) is not None

    def revoke_all(self) -> int:
        """End every session; how many were open (expired ones not counted)."""
        self._drop_expired()
        count = len(self._live)
        self._live.clear()
        return count

    def _drop_expired(self) -> None:
        now = self.clock()
        while self._live and next(iter(self._live.values())).expires <= now:
            self._live.popitem(last=False)


def client_of(scope: Scope) -> str:
    """The address a request came from ('' when the server does not know it)."""
    client = scope.get("client")
    return str(client[0]) if client else ""


class SessionCookies:
    """ASGI middleware in front of the :class:`~shared.http.Guard`: a request's cookies
    lose any read-only session value of the guard's (``aesop_session``, ``__Host-``
    too), and a request whose cookie named ``port`` holds a session live for its
    address gains that value, so the guard lets it read; the session goes in the scope
    (``SCOPE_KEY``), so that a WebSocket ends with it. Without a token there is nothing
    to do."""

    def __init__(self, app: ASGIApp, *, sessions: Sessions, token: SecretStr | None,
                 port: int) -> None:
        self.app, self.sessions = app, sessions
        self.value = session_value(token) if token is not None else None
        self.names = (cookie_name(port, secure=False), cookie_name(port, secure=True))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if self.value is not None and scope["type"] in ("http", "websocket"):
            scope = self._translate(scope)
        await self.app(scope, receive, send)

    def _translate(self, scope: Scope) -> Scope:
        headers = [(k, v) for k, v in scope["headers"] if k != b"cookie"]
        kept: list[str] = []
        live: str | None = None
        for raw in (v for k, v in scope["headers"] if k == b"cookie"):
            for part in raw.decode("latin-1").split(";"):
                name, _, value = part.strip().partition("=")
                if name in (SESSION_COOKIE, SECURE_SESSION_COOKIE):
                    continue  # only this middleware may bring one
                if name in self.names and live is None \
                        and self.sessions.valid(value, client_of(scope)):
                    live = value
                if part.strip():
                    kept.append(part.strip())
        if live is not None:
            kept.append(f"{SESSION_COOKIE}={self.value}")
        if kept:
            headers.append((b"cookie", "; ".join(kept).encode("latin-1")))
        return {**scope, "headers": headers, SCOPE_KEY: live}
