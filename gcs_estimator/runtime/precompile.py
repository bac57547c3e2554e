"""Compile the kernels once, ahead of the first run: `python -m gcs_estimator.runtime.precompile`.

numba compiles the filter kernels, the simulator's integrator and the refinement's filters
(output error's and filter error's) on first use and caches them on disk; on a fresh
install that first use is the first `listen` or `demo`, which would wait about half a
minute before its listening line. `./run` calls this right after installing, so the wait
comes with the install, once, and says so.
"""

from __future__ import annotations

import contextlib
import io
import time
import warnings

import numpy as np


def main() -> int:
    from gcs_estimator.config import load_config
    from gcs_estimator.ingest.telemetry import tlog_fast
    from gcs_estimator.refine import RefineError, refine_run
    from gcs_estimator.runtime.session import run_recording, warm_up
    from sim.truth import simulate

    start = time.perf_counter()
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=2"])
    warm_up(config)
    tlog_fast.warm_up()  # the tlog reader's kernel
    flight = simulate(config, seed=1)
    # Its results (the structure check's replays compile the block kernel too) say what
    # they do on stderr: not news while the install compiles.
    with contextlib.redirect_stderr(io.StringIO()):
        result = run_recording(config, flight.t_s, flight.inputs, flight.measurements).result
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")  # two seconds identify little: only the compile counts
        refine_run(result, "output-error")
        with contextlib.suppress(RefineError):  # the filter-error kernel is compiled by then
            refine_run(result, "filter-error")
    assert np.isfinite(result.filters["IEKF"].coefficients).all()
    print(f"compiled the kernels in {time.perf_counter() - start:.1f} s (cached for every run)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
