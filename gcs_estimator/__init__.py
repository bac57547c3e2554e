"""gcs-estimator: aerodynamic coefficients from MAVLink telemetry, live, with an EKF and an
iterated EKF side by side.

The folders follow the data, each importing only from those above it (tests/test_layout.py):

    arrays, units, frames, stop, schema,   shared types and small utilities
    blas, differences
    model/, config                         the aircraft's equations and its airframe file
    ingest/                                every source: endpoints, MAVLink, tlogs, logs, data files
    estimation/                            the filters, the estimator, restarts, warm start, noise
    uncertainty/                           the sigma to trust, the marks, the structure check
    refine/                                the whole-record maximum-likelihood fit
    outputs/                               the table, results files, history and the Rerun view
    runtime/                               the session loop, worker processes, batches
    cli, __main__                          the commands; which process runs what is chosen here

Importing the package points numba's on-disk cache of compiled kernels at a folder named
after a hash of the package's sources (and the simulator's). numba notices a change in
the file that holds a compiled function, but not in the functions it calls from other
files: after an update of model/equations.py alone, the filter kernel cached from
estimation/filters/fast.py would run the old equations. A folder per source state cannot
be stale. A NUMBA_CACHE_DIR set by the user is left as it is.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from pathlib import Path

_CACHE_PREFIX = "numba-"


def _kernel_cache_dir() -> Path:
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for package in (here, here.parent / "sim"):
        for source in sorted(package.rglob("*.py")):
            digest.update(source.relative_to(package.parent).as_posix().encode())
            digest.update(source.read_bytes())
    name = _CACHE_PREFIX + digest.hexdigest()[:16]
    parent = here / "__pycache__"
    try:
        parent.mkdir(exist_ok=True)
        usable = os.access(parent, os.W_OK)
    except OSError:
        usable = False
    if not usable:  # an installation this user cannot write to
        parent = Path.home() / ".cache" / "gcs-estimator"
    for old in parent.glob(_CACHE_PREFIX + "*"):  # caches of earlier sources
        if old.name != name:
            shutil.rmtree(old, ignore_errors=True)
    return parent / name


if "NUMBA_CACHE_DIR" not in os.environ:
    os.environ["NUMBA_CACHE_DIR"] = str(_kernel_cache_dir())
    if "numba" in sys.modules:  # imported first: its config has read the environment
        from numba.core import config as _numba_config

        setattr(_numba_config, "CACHE_DIR", os.environ["NUMBA_CACHE_DIR"])  # noqa: B010
