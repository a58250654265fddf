"""Clocks of the live runner: the real monotonic clock and a virtual (discrete-event) clock.

Both have ``now()`` (seconds) and ``sleep_until(t, stop)`` (return at time ``t`` or as soon as
the :class:`threading.Event` ``stop`` is set). The runner's threads only ever block in
``sleep_until`` (or in a camera read), so the same code runs in real time or, with
:class:`VirtualClock`, as fast as the machine can go with exact, reproducible timing (the soak
test replays a quarter of an hour of camera frames in well under a minute of wall time this way).
"""

from __future__ import annotations

import threading
import time

__all__ = ["RealClock", "VirtualClock"]


class RealClock:
    """``time.perf_counter`` with precise sleeps.

    ``sleep_until`` waits on the stop event until ``spin`` seconds before the deadline and then
    polls the clock (yielding the GIL between polls), which keeps the wake-up error near the
    clock's resolution instead of the scheduler's timer slack (~0.1 ms) without busy-waiting
    for long. The clock is system-wide (``CLOCK_MONOTONIC`` on Linux), so a worker process's
    capture times (:class:`phjax.live.WorkerSource`) are on the same clock.

    Arguments:
        spin: seconds before a deadline at which the sleep switches to polling (default 0.4 ms).
    """

    virtual = False

    def __init__(self, spin: float = 4e-4):
        self.spin = float(spin)

    @staticmethod
    def now() -> float:
        return time.perf_counter()

    def sleep_until(self, t: float, stop: threading.Event | None = None) -> None:
        while True:
            remaining = t - time.perf_counter()
            if remaining <= 0 or (stop is not None and stop.is_set()):
                return
            if remaining > self.spin:
                if stop is not None:
                    stop.wait(remaining - self.spin)
                else:
                    time.sleep(remaining - self.spin)
            else:
                time.sleep(0)  # yield the GIL, then poll again

    def register(self) -> None:  # the virtual clock's participant protocol (no-op here)
        pass

    def unregister(self) -> None:
        pass


class VirtualClock:
    """A discrete-event clock shared by the runner's threads.

    Each thread that sleeps on the clock calls :meth:`register` first and :meth:`unregister`
    when it ends. Time stands still while any registered thread is working; when all of them
    are asleep in :meth:`sleep_until`, time jumps to the earliest wake-up time. Work therefore
    takes no virtual time, deadlines are met exactly and the run is as fast as the CPU allows.

    Arguments:
        t0: start time, s.
    """

    virtual = True

    def __init__(self, t0: float = 0.0):
        self._now = float(t0)
        self._cv = threading.Condition()
        self._participants = 0
        self._waiting: dict[int, float] = {}

    def now(self) -> float:
        return self._now

    def register(self) -> None:
        with self._cv:
            self._participants += 1

    def unregister(self) -> None:
        with self._cv:
            self._participants -= 1
            self._advance()

    def _advance(self) -> None:
        # caller holds the lock
        if self._waiting and len(self._waiting) >= self._participants:
            self._now = max(self._now, min(self._waiting.values()))
            self._cv.notify_all()

    def sleep_until(self, t: float, stop: threading.Event | None = None) -> None:
        me = threading.get_ident()
        with self._cv:
            if t <= self._now:
                return
            self._waiting[me] = t
            try:
                self._advance()
                while self._now < t and not (stop is not None and stop.is_set()):
                    self._cv.wait(0.05)
            finally:
                del self._waiting[me]

    def wake(self) -> None:
        """Wake every sleeper (after setting a stop event)."""
        with self._cv:
            self._cv.notify_all()
