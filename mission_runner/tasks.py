"""Task ownership helpers: every task belongs to a task group, so nothing runs unowned and no
failure goes unseen (components keep theirs with the ``AsyncExitStack`` + ``TaskGroup`` idiom).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Mapping
from typing import TypeVar

_T = TypeVar("_T")


async def first_completed(contenders: Mapping[str, Awaitable[_T]]) -> tuple[str, _T]:
    """``(name, result)`` of whichever of ``contenders`` (task name -> awaitable) completes first.

    They run side by side in one task group; the others are cancelled and have ended when this
    returns. An error of any contender ends the race and is raised as itself (several at once, as
    an exception group), never dropped with the losers.
    """
    first: asyncio.Future[tuple[str, _T]] = asyncio.get_running_loop().create_future()

    async def contend(name: str, awaitable: Awaitable[_T]) -> None:
        result = await awaitable
        if not first.done():
            first.set_result((name, result))

    failure: BaseException | None = None
    try:
        async with asyncio.TaskGroup() as group:
            tasks = [
                group.create_task(contend(name, a), name=name) for name, a in contenders.items()
            ]
            try:
                await first
            finally:
                for task in tasks:
                    task.cancel()
    except BaseExceptionGroup as errors:
        if len(errors.exceptions) > 1:
            raise
        failure = errors.exceptions[0]
    if failure is not None:
        raise failure  # outside the handler, so that it does not read as a second error
    return first.result()
