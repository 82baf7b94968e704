"""Stopping an outlet's tasks when a library may swallow a cancellation.

On Python 3.11 ``asyncio.wait_for`` returns normally when the awaited call completes in the same step as a
``cancel()`` (gh-86296); aiomqtt waits for every acknowledgement that way. A sender task cancelled while a
publish was being acknowledged then went on and waited for the next message for ever, and the outlet's
``close()`` with it (a CI run hung for 300 s). Two defences, both here:

- ``raise_if_cancelled()`` in a task's own loop: the task knows it was asked to stop even when one await
  consumed the ``CancelledError`` (``Task.cancelling()``);
- ``stop_tasks()`` cancels, waits a bounded time, cancels again the tasks that are still running, and gives
  up on them after ``timeout_s`` instead of waiting for ever.
"""

from __future__ import annotations

import asyncio
from collections.abc import Collection
from typing import Any

__all__ = ["raise_if_cancelled", "stop_tasks"]


def raise_if_cancelled() -> None:
    """Raise ``CancelledError`` in a task that was cancelled, even if an await swallowed the cancellation."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


async def stop_tasks(
    tasks: Collection[asyncio.Task[Any]], *, timeout_s: float, again_every_s: float = 2.0
) -> set[asyncio.Task[Any]]:
    """Cancel ``tasks`` and wait until they end, cancelling again every ``again_every_s`` the ones still
    running (a second cancel reaches a task that swallowed the first). The tasks' own errors are retrieved,
    not raised (a failure was reported by the task). Returns the tasks abandoned after ``timeout_s``."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    pending = {t for t in tasks if not t.done()}
    while pending:
        left = deadline - loop.time()
        if left <= 0:
            break
        for task in pending:
            task.cancel()
        _, pending = await asyncio.wait(pending, timeout=min(again_every_s, left))
    for task in tasks:
        if task.done() and not task.cancelled():
            task.exception()
    return pending
