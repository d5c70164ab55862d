"""Progress of a tracking run on stderr: a self-overwriting line on a terminal (10 times a second at most),
otherwise one plain line every `every_s` seconds (nothing for a short run), so that a long `flextrack track`,
replayed or live, is never silent until it ends."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

from flextrack.runners.live import Progress
from flextrack.runners.session import print_progress

TTY_EVERY_S = 0.1


class ProgressPrinter:
    def __init__(self, stream=None, every_s: float = 5.0, clock: Callable[[], float] = time.monotonic,
                 tty: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty() if tty is None else tty
        self.every_s = TTY_EVERY_S if self.tty else every_s
        self.clock = clock
        self._last = clock()

    def __call__(self, p: Progress) -> None:
        now = self.clock()
        done = p.t_s >= p.total_s
        if now - self._last < self.every_s and not (done and self.tty):
            return
        self._last = now
        if self.tty:
            print_progress(p, self.stream)
            return
        share = 100.0 * p.t_s / p.total_s if p.total_s > 0 else 100.0
        self.stream.write(f"  t {p.t_s:.1f}/{p.total_s:.1f} s ({share:.0f} %), {len(p.record.rows)} frames, "
                          f"{p.record.requests} requests, {p.record.responses} answers, {p.status}\n")
        self.stream.flush()
