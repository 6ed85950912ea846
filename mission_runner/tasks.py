"""Task ownership helpers: every task belongs to a task group, so nothing runs unowned and no
failure goes unseen (see also the components' ``AsyncExitStack`` + ``TaskGroup`` idiom).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Mapping
from typing import Any


async def first_completed(awaitables: Mapping[str, Awaitable[Any]]) -> tuple[str, Any]:
    """Run ``{name: awaitable}`` side by side in one task group; when the first finishes, cancel
    the others and return ``(name, result)``. A failure of any of them propagates (as the task
    group's exception group) instead of being dropped with the losers.
    """
    winner: list[tuple[str, Any]] = []

    async def race(name: str, awaitable: Awaitable[Any]) -> None:
        result = await awaitable
        if not winner:
            winner.append((name, result))
            for other, task in tasks.items():
                if other != name:
                    task.cancel()

    tasks: dict[str, asyncio.Task[None]] = {}
    async with asyncio.TaskGroup() as group:
        for name, awaitable in awaitables.items():
            tasks[name] = group.create_task(race(name, awaitable), name=name)
    return winner[0]
