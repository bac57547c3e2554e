"""`gcs-estimator` and `python -m gcs_estimator`: signal handlers first, then the commands."""

from __future__ import annotations

import sys

from gcs_estimator.stop import PROCESS_STOP


def entrypoint() -> None:
    PROCESS_STOP.install()
    from gcs_estimator.cli import main

    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
