"""Per-session state on the server (region's colour histograms, the chained estimator's request count),
bounded in count and in age.

A session's state is its own and never shared: the key is the request's `session_id` with the object id.
Entries unused for `max_age_s` are dropped, and past `max_sessions` the least recently used one is
evicted; an unknown (or evicted) session starts fresh.
Thread-safe: the service may call the estimator from several worker threads.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Generic, TypeVar

V = TypeVar("V")


class SessionStore(Generic[V]):
    def __init__(self, factory: Callable[[], V], max_sessions: int = 1024, max_age_s: float = 600.0,
                 clock: Callable[[], float] = time.monotonic):
        if max_sessions < 1 or max_age_s <= 0:
            raise ValueError("a session store needs max_sessions >= 1 and max_age_s > 0")
        self.factory = factory
        self.max_sessions = max_sessions
        self.max_age_s = max_age_s
        self.clock = clock
        self._entries: OrderedDict[tuple, tuple[float, V]] = OrderedDict()  # oldest use first
        self._lock = threading.Lock()

    def get(self, key: tuple) -> tuple[V, bool]:
        """The session's state and whether it is new (unknown, expired or evicted before)."""
        now = self.clock()
        with self._lock:
            self._expire(now)
            entry = self._entries.pop(key, None)
            fresh = entry is None
            value = self.factory() if fresh else entry[1]
            self._entries[key] = (now, value)
            while len(self._entries) > self.max_sessions:
                self._entries.popitem(last=False)
            return value, fresh

    def _expire(self, now: float) -> None:
        while self._entries:
            key, (used, _) = next(iter(self._entries.items()))
            if now - used <= self.max_age_s:
                break
            del self._entries[key]

    def __len__(self) -> int:
        with self._lock:
            self._expire(self.clock())
            return len(self._entries)

    def __contains__(self, key: tuple) -> bool:
        with self._lock:
            self._expire(self.clock())
            return key in self._entries
