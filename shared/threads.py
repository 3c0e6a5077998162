"""Work on a thread of its own, awaited from the event loop."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


async def on_fresh_thread(fn: Callable[..., T], *args: Any) -> T:
    """Run ``fn`` on a new thread that ends with it. Heavy admin work that uses OpenMP
    (leave-one-out, loading a model) runs so: libgomp keeps a team of threads per calling
    thread for as long as that thread lives, and a second long-lived team doubled the
    compute thread's embedding time; a short-lived thread takes its team with it."""
    loop = asyncio.get_running_loop()
    future: asyncio.Future[T] = loop.create_future()

    def settle(result: Any, error: BaseException | None) -> None:
        if future.done():
            return
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)

    def run() -> None:
        try:
            result = fn(*args)
        except BaseException as exc:  # handed to the awaiting coroutine
            loop.call_soon_threadsafe(settle, None, exc)
        else:
            loop.call_soon_threadsafe(settle, result, None)

    threading.Thread(target=run, name="aesop-oneoff", daemon=True).start()
    return await future
