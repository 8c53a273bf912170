"""Frame times of a fixed-rate stream: when each frame is due, and which frames a late reader skips."""

from __future__ import annotations

import time

import numpy as np

from lightplane.core.errors import LightplaneError

__all__ = ["Pacer"]


class Pacer:
    """Frame times of a fixed-rate stream and the frames a late reader skips.

    ``queue`` frames wait for the reader, as in a camera driver's queue of buffers: a reader that is late
    gets the oldest frame still queued (its exposure time says how late), and only frames pushed out of the
    queue are skipped.  ``queue=1`` keeps nothing but the newest frame."""

    def __init__(self, fps: float | None, queue: int = 1) -> None:
        if fps is not None and not (np.isfinite(fps) and fps > 0):
            raise LightplaneError(f"fps must be a positive number of frames per second, got {fps!r}")
        if not (isinstance(queue, (int, np.integer)) and 1 <= queue <= 1024):
            raise LightplaneError(f"queue must be 1 to 1024 frames, got {queue!r}")
        self.queue = int(queue)
        self.fps = None if fps is None else float(fps)
        self.t0: float | None = None
        self.next = 0

    def start(self) -> None:
        self.t0 = time.monotonic()
        self.next = 0

    def take(self, timeout: float | None) -> tuple[int, float, int]:
        """``(index, t_exposure, skipped)``: the frame to deliver now (waiting for it when early) and how
        many frames were skipped since the last one.  Raises TimeoutError past ``timeout``."""
        if self.t0 is None:
            self.start()
        assert self.t0 is not None
        now = time.monotonic()
        if self.fps is None:
            k = self.next
            self.next += 1
            return k, now, 0
        due = int(np.floor((now - self.t0) * self.fps))
        k = max(self.next, due - self.queue + 1)
        t = self.t0 + k / self.fps
        if t > now:
            wait = t - now
            if timeout is not None and wait > timeout:
                time.sleep(max(timeout, 0.0))
                raise TimeoutError("no frame in time")
            time.sleep(wait)
        skipped = k - self.next
        self.next = k + 1
        return k, t, skipped

    def rebase(self) -> None:
        """Start the clock anew at the next frame (after a stall that is not the reader's: no drops)."""
        if self.fps is not None:
            self.t0 = time.monotonic() - self.next / self.fps
