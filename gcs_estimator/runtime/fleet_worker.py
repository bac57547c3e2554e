"""What each Dask worker of a batch does once, before its first log (decision 0055).

A fresh worker process would otherwise pay its start-up inside its first task, or, worse,
between the scheduler handing it the task and the task's clock starting: importing the
estimator (pymavlink's dialect, numba, scipy: over a second), loading the compiled
kernels (the filters' and the tlog reader's) from numba's on-disk cache, and, for a
process whose objects were never frozen, the garbage collector's full collections over
all of that in the middle of every log. The plugin does it as the worker joins the
batch (registering it waits for the workers there; one that joins later, or replaces a
killed one, runs it before it takes a task): session.warm_up (kernels, then gc.freeze)
and tlog_fast.warm_up. The batch's client prepares itself first (fleet.connect): on a
cache miss it compiles the kernels once, and workers that share its file system then
load them instead of each compiling them at once.
"""

from __future__ import annotations

import asyncio
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from gcs_estimator import blas
from gcs_estimator.config import AircraftConfig


class PrepareWorker(WorkerPlugin):
    """Imports and compiled kernels loaded, the collector's objects frozen."""

    name = "gcs-estimator-prepare"

    def __init__(self, config: AircraftConfig) -> None:
        self.config = config

    async def setup(self, worker: Any) -> None:
        """In a thread: a compile on a cache miss takes minutes on a busy machine, and the
        worker's event loop must go on answering the scheduler meanwhile."""
        await asyncio.to_thread(prepare, self.config)


def prepare(config: AircraftConfig) -> None:
    """This process ready to estimate logs: one BLAS thread, the estimator imported, its
    kernels loaded (compiled on a cache miss), then the start-up's objects frozen out of
    the garbage collector (last: it freezes what is there)."""
    blas.one_thread()
    from gcs_estimator.ingest.telemetry import tlog_fast
    from gcs_estimator.runtime import logs  # noqa: F401  (what each task runs)
    from gcs_estimator.runtime.session import warm_up

    tlog_fast.warm_up()
    warm_up(config)
