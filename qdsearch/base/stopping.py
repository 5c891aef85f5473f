"""Ctrl-C and SIGTERM, acted on only where stopping is safe: the one `STOP` of a process, which
the script installs and every wait (for a cluster, for results, between videos) consults, as
does an experiment between two runs it opens.

Map: `StopRequests` (record a request; `check` it; `interruptible` blocks), `STOP`; `Stopped`
(a stop whose line has been said).
"""

from __future__ import annotations

import contextlib
import signal
from typing import Any, Iterator


class StopRequests:
    """Ctrl-C and SIGTERM, acted on only where stopping is safe.

    A signal only records the request, except inside `interruptible()` (waiting for the cluster),
    where it stops the wait at once. So a stop never cuts a checkpoint write, an import or a tell
    in half: the iteration in flight is abandoned and the last completed one is kept.
    """

    def __init__(self) -> None:
        self.requested = False
        self._raise_now = False

    def install(self) -> None:
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self._on_signal)

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.requested = True
        if self._raise_now:
            self._raise_now = False
            raise KeyboardInterrupt

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        self.check()
        self._raise_now = True
        try:
            yield
        finally:
            self._raise_now = False


STOP = StopRequests()


class Stopped(KeyboardInterrupt):
    """A stop that has said its own line (where the run folders are, how to go on): the script
    adds none."""
