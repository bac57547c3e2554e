"""One BLAS thread: the project's matrices are at most tens of rows, where BLAS's own
threads never pay for themselves. Worse, OpenBLAS's threads spin after every call while
they wait for the next, so on a small machine they take the cores that refine's threads,
the station's worker processes and the simulator need (measured on 2 cores: a
filter-error fit in two threads took as long as in one until the spinning stopped).

Each process the project starts (the command line, its worker processes) calls
one_thread() first; refine() also holds the limit while it runs, for programs that call
it as a library.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

from threadpoolctl import threadpool_limits

P = ParamSpec("P")
R = TypeVar("R")


def _load() -> None:
    """Load the BLAS libraries numpy and scipy bring, so that the limit reaches both
    (threadpoolctl sets the libraries loaded when it is called)."""
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401


def one_thread() -> None:
    """Limit every BLAS library of this process to one thread, for its lifetime."""
    _load()
    threadpool_limits(limits=1, user_api="blas")


def one_thread_during(fn: Callable[P, R]) -> Callable[P, R]:
    """fn with every BLAS library at one thread while it runs, as it was after."""

    @functools.wraps(fn)
    def limited(*args: P.args, **kwargs: P.kwargs) -> R:
        _load()
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return limited
