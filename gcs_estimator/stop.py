"""The stop request: set by SIGINT/SIGTERM, checked by every loop that can wait.

A module with no heavy imports, so that the command line installs its handlers before
anything else is loaded (importing the estimator takes about a second): a signal at any
point of start-up ends the run cleanly instead of killing it.
"""

from __future__ import annotations

import signal
from types import FrameType


class Stop:
    """Set by SIGINT/SIGTERM (once installed); sources check it and end cleanly."""

    def __init__(self) -> None:
        self.requested = False
        self.count = 0
        """Signals so far (a wait after the run, such as a served view's, ends at the next)."""

    def install(self) -> Stop:
        def handler(signum: int, frame: FrameType | None) -> None:
            self.requested = True
            self.count += 1

        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)
        return self


PROCESS_STOP = Stop()
"""The command line's stop request (installed by gcs_estimator.__main__.entrypoint)."""
