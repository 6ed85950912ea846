"""Task ownership helpers: every task belongs to a task group, so nothing runs unowned and no
failure goes unseen (see also the components' ``AsyncExitStack`` + ``TaskGroup`` idiom).
"""

import asyncio


async def first_completed(awaitables):
    """Run ``{name: awaitable}`` side by side in one task group; when the first finishes, cancel
    the others and return ``(name, result)``. A failure of any of them propagates (as the task
    group's exception group) instead of being dropped with the losers.
    """
    winner = []

    async def race(name, awaitable):
        result = await awaitable
        if not winner:
            winner.append((name, result))
            for other, task in tasks.items():
                if other != name:
                    task.cancel()

    tasks = {}
    async with asyncio.TaskGroup() as group:
        for name, awaitable in awaitables.items():
            tasks[name] = group.create_task(race(name, awaitable), name=name)
    return winner[0]
