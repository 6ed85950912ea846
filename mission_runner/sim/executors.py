"""Where a sweep's runs are computed: here, one after another (:class:`InProcess`, the default), or
on a Dask cluster (:class:`DaskExecutor`: a scheduler at an address, or a ``LocalCluster`` it
starts and stops). Both take pure functions and give the results in submission order, so what a
sweep writes does not depend on where its runs went.

Dask is an optional extra (``pip install "mission-runner[cluster]"``): it is imported only when
a cluster is used, and :func:`open_executor` falls back to :class:`InProcess` when a sweep too
small to pay for a cluster's start does not ask for one.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from types import TracebackType
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from ..errors import ClusterError, RunError

if TYPE_CHECKING:
    from distributed import Client, Future, LocalCluster

_A = TypeVar("_A")
_R = TypeVar("_R")

#: A sweep of at least this many simulator steps in all (combinations x ``timing.steps``) starts a
#: ``LocalCluster`` when no ``--cluster`` is given, Dask is installed and there are 2 cores or more.
#: A step of the 4-vehicle paper scenario takes about 2.5 ms, so this is some 10 s of work, and a
#: LocalCluster takes 2-4 s to start on a busy 2-core machine.
LOCAL_CLUSTER_FROM_STEPS = 4000
#: How long to wait for a scheduler to answer before giving up on an address.
CONNECT_TIMEOUT_S = 10.0

#: ``on_done(done, total)``: after each finished run, in the order they finish.
OnDone = Callable[[int, int], None]

log = logging.getLogger(__name__)


class Executor(Protocol):
    """Runs ``function`` on every item; results in the items' order, whatever order they end in."""

    def map_in_order(
        self,
        function: Callable[[_A], _R],
        items: Sequence[_A],
        names: Sequence[str],
        on_done: OnDone | None = None,
    ) -> list[_R]:
        """``[function(item) for item in items]``. A failure raises :class:`RunError` naming
        the item (``names[i]``: its parameters and seed) with the item's error as its cause."""
        ...


class InProcess:
    """Every run here, one after another: the path sweeps have always taken."""

    def map_in_order(
        self,
        function: Callable[[_A], _R],
        items: Sequence[_A],
        names: Sequence[str],
        on_done: OnDone | None = None,
    ) -> list[_R]:
        results = []
        for index, (item, name) in enumerate(zip(items, names, strict=True)):
            try:
                results.append(function(item))
            except Exception as error:
                raise RunError(name, error) from error
            if on_done is not None:
                on_done(index + 1, len(items))
        return results


class DaskExecutor:
    """Runs on a Dask cluster: the scheduler at ``address`` (``tcp://host:8786``), or, with
    ``address=None``, a ``LocalCluster`` of ``workers`` processes (one thread each) that this
    starts on entering and closes on leaving. A context manager: the client, and the cluster if it
    is ours, are closed on the way out, Ctrl-C included (the runs not yet done are cancelled)."""

    def __init__(
        self, address: str | None, workers: int = 2, timeout_s: float = CONNECT_TIMEOUT_S
    ) -> None:
        self.address = address
        self.workers = workers
        self.timeout_s = timeout_s
        self.cluster: LocalCluster | None = None
        self._client: Client | None = None

    def __enter__(self) -> DaskExecutor:
        # Optional and slow to import (~0.5 s): only a sweep sent to a cluster needs it.
        import distributed  # noqa: PLC0415 - optional extra, imported only for a cluster

        _quiet_distributed()
        try:
            if self.address is None:
                self.cluster = distributed.LocalCluster(
                    n_workers=self.workers,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=":0",  # a free port: 8787 may be taken
                    # Its workers log heartbeats lost at Ctrl-C as tracebacks; a run's own
                    # failure comes back as a RunError naming it, so they have nothing to add.
                    silence_logs=logging.CRITICAL,
                )
            self._client = distributed.Client(
                self.cluster or self.address, timeout=self.timeout_s, set_as_default=False
            )
        except (OSError, TimeoutError) as error:
            self._close()
            where = self.address or "a LocalCluster"
            raise ClusterError(
                f"no Dask scheduler answered at {where} within {self.timeout_s:g} s ({error}): "
                "start one (`dask scheduler`) or check --cluster"
            ) from error
        except BaseException:
            self._close()
            raise
        scheduler = self.address if self.cluster is None else self.cluster.scheduler_address
        workers = len(self._client.scheduler_info().get("workers", {}))
        log.info("runs on the Dask cluster at %s (%d workers)", scheduler, workers)
        if workers == 0:  # not an error: workers may join later, and the runs wait for them
            log.warning("the scheduler at %s has no workers yet: the runs wait for one", scheduler)
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self._close()

    def _close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
        if self.cluster is not None:
            self.cluster.close()

    def map_in_order(
        self,
        function: Callable[[_A], _R],
        items: Sequence[_A],
        names: Sequence[str],
        on_done: OnDone | None = None,
    ) -> list[_R]:
        from distributed import as_completed  # noqa: PLC0415 - optional extra (see __enter__)

        if self._client is None:
            raise RuntimeError("DaskExecutor used outside its `with` block")
        futures = [self._client.submit(function, item, pure=False) for item in items]
        index_of = {future.key: index for index, future in enumerate(futures)}
        results: list[Any] = [None] * len(futures)
        try:
            completed = as_completed(futures, loop=self._client.loop)
            for done, future in enumerate(completed, start=1):
                index = index_of[future.key]
                results[index] = _result(future, names[index])
                if on_done is not None:
                    on_done(done, len(futures))
        finally:
            # A failure, Ctrl-C or a callback's error: stop what has not run yet (a no-op when
            # every run is done), so a remote cluster does not go on computing for nobody.
            self._client.cancel(futures)
        return results


def _result(future: Future[_R], name: str) -> _R:
    """``future``'s result, or a :class:`RunError` naming the run when it failed on a worker."""
    if future.status == "error":
        error = future.exception()
        raise RunError(name, error) from error
    return future.result()


def _quiet_distributed() -> None:
    """Dask logs every worker's start and stop at INFO; a sweep's own progress is enough."""
    if logging.getLogger("distributed").getEffectiveLevel() < logging.WARNING:
        logging.getLogger("distributed").setLevel(logging.WARNING)


def dask_installed() -> bool:
    """Whether ``dask[distributed]`` can be imported (without importing it)."""
    return importlib.util.find_spec("distributed") is not None


def open_executor(
    cluster: str | None,
    workers: int | None,
    steps: int,
    runs: int,
    timeout_s: float = CONNECT_TIMEOUT_S,
) -> AbstractContextManager[Executor]:
    """The executor a sweep asked for. ``cluster``: ``"none"`` (here), ``"local"`` (a new
    ``LocalCluster``), a scheduler's address, or None (a ``LocalCluster`` from
    :data:`LOCAL_CLUSTER_FROM_STEPS` steps in all, else here). ``workers``: the LocalCluster's
    processes (default: the cores, at most ``runs``, the number of independent runs).
    ``timeout_s``: how long a scheduler has to answer."""
    cores = os.cpu_count() or 1
    if cluster is None:
        big = steps >= LOCAL_CLUSTER_FROM_STEPS and runs >= 2 and cores >= 2
        cluster = "local" if big and dask_installed() else "none"
    if cluster == "none":
        return _here()
    if not dask_installed():
        raise ClusterError(
            f"--cluster {cluster} needs Dask: pip install 'mission-runner[cluster]' "
            "(or 'dask[distributed]')"
        )
    if cluster == "local":
        return DaskExecutor(None, workers or max(1, min(cores, runs)), timeout_s)
    return DaskExecutor(cluster, timeout_s=timeout_s)


@contextmanager
def _here() -> Iterator[Executor]:
    yield InProcess()
