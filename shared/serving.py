"""Running a service's app with uvicorn, with the limits a public port needs.

uvicorn bounds neither the connections it holds nor how long a client may take to send
its request's headers (issue 26: 1,500 slow connections were all still held after 50 s).
:func:`serve` runs it with

* ``limit_concurrency``: past :data:`MAX_CONNECTIONS` connections or requests at once, a
  new request is answered 503 at once;
* a **header timeout**: a connection whose request line and headers are not complete
  :data:`HEADER_TIMEOUT_S` after it opened (or after its previous response) is closed
  (:class:`HeaderTimeout`, uvicorn's h11 protocol with one timer more);
* ``timeout_keep_alive``: an idle kept-alive connection is closed after
  :data:`KEEP_ALIVE_S`.

The body is the app's to time (``shared.http.Guard``).
"""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import FastAPI
from uvicorn.protocols.http.h11_impl import H11Protocol

from .settings import ServiceSettings

HEADER_TIMEOUT_S = 10.0
KEEP_ALIVE_S = 5.0
MAX_CONNECTIONS = 256


class HeaderTimeout(H11Protocol):
    """uvicorn's HTTP/1.1 protocol, closing a connection whose headers are late."""

    header_timeout_s = HEADER_TIMEOUT_S

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._headers_due: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self._between_requests():
            self._arm()  # a new request begins: its headers are due
        super().data_received(data)
        if not self._between_requests():
            self._disarm()  # its headers are in

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _between_requests(self) -> bool:
        return self.cycle is None or self.cycle.response_complete

    def _arm(self) -> None:
        if self._headers_due is None:
            self._headers_due = self.loop.call_later(self.header_timeout_s, self._late)

    def _disarm(self) -> None:
        if self._headers_due is not None:
            self._headers_due.cancel()
            self._headers_due = None

    def _late(self) -> None:
        self._headers_due = None
        if self._between_requests() and not self.transport.is_closing():
            self.transport.close()


def header_timeout(seconds: float) -> type[HeaderTimeout]:
    """:class:`HeaderTimeout` with its own timeout (tests use a short one)."""
    return type("HeaderTimeout", (HeaderTimeout,), {"header_timeout_s": seconds})


def server(app: FastAPI, host: str, port: int, *, log_level: str = "info",
           header_timeout_s: float = HEADER_TIMEOUT_S,
           limit_concurrency: int = MAX_CONNECTIONS) -> Any:
    """A ``uvicorn.Server`` for ``app`` with the limits above (not started)."""
    import uvicorn

    # log_config=None: uvicorn's lines go to the root logger, in the process's one format
    # (shared.logs), not in a second one of its own
    config = uvicorn.Config(app, host=host, port=port, log_level=log_level, access_log=False,
                            log_config=None,
                            http=header_timeout(header_timeout_s),
                            limit_concurrency=limit_concurrency,
                            timeout_keep_alive=int(KEEP_ALIVE_S))
    return uvicorn.Server(config)


def serve(app: FastAPI, settings: ServiceSettings) -> None:
    """Run ``app`` until SIGINT/SIGTERM, refusing off-loopback exposure without a token."""
    settings.check_exposure()
    server(app, settings.host, settings.port, log_level=settings.log_level).run()
