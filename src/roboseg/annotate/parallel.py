"""PNG mask pairs of the kept frames, rendered in order in-process or by a pool of processes.

Masks depend only on a frame's joints (the calibration and cameras are fixed per recording), so
they can be rendered ahead of the MCAP copy that consumes them. With ``workers > 1`` batches of
frames go to worker processes (``fork`` where available, so the robot model is not pickled);
at most ``ahead`` batches are in flight and results the copy has not asked for yet are held in
a bounded buffer, so memory does not grow with the recording length.
"""

from __future__ import annotations

import logging
import multiprocessing
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Protocol

import numpy as np
import torch

log = logging.getLogger(__name__)

MaskPair = list[bytes | None]  # [left png, right png]; None once written


class PairEncoder(Protocol):
    """What renders one frame: URDF-ordered joints per robot -> (left, right) PNG bytes."""

    def encode(self, joints: dict[str, np.ndarray], level: int) -> tuple[bytes, bytes]: ...


_WORKER: tuple[PairEncoder, int] | None = None


def _init_worker(encoder: PairEncoder, level: int) -> None:
    """Pool initializer: one torch thread per worker (the pool is the parallelism)."""
    global _WORKER
    torch.set_num_threads(1)
    _WORKER = (encoder, level)


def _encode_batch(batch: list[dict[str, np.ndarray]]) -> list[tuple[bytes, bytes]]:
    assert _WORKER is not None, "worker not initialised"
    encoder, level = _WORKER
    return [encoder.encode(joints, level) for joints in batch]


def _context() -> multiprocessing.context.BaseContext:
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


class MaskStream:
    """``get(k)``: the PNG pair of kept frame ``k`` (frames are asked for in about increasing
    order; any frame can be asked for again, it is then rendered in-process).

    Args:
        encoder: renders one frame (pickled to the workers only without ``fork``).
        joints: URDF-ordered joints per robot of every kept frame.
        level: PNG zlib level.
        workers: processes rendering ahead; ``<= 1`` renders in the calling process on demand.
        batch: frames per task sent to a worker.
        ahead: tasks in flight per worker.
    """

    def __init__(
        self,
        encoder: PairEncoder,
        joints: Sequence[dict[str, np.ndarray]],
        level: int,
        workers: int = 1,
        batch: int = 4,
        ahead: int = 3,
    ) -> None:
        self.encoder, self.joints, self.level = encoder, joints, level
        self.batch = max(1, batch)
        self._ready: dict[int, MaskPair] = {}
        self._futures: deque[tuple[int, Future]] = deque()
        self._next_submit = 0  # first frame not yet submitted
        self._next_collect = 0  # first frame not yet collected
        self._pool: ProcessPoolExecutor | None = None
        self._window = 0
        if workers > 1 and len(joints) > self.batch:
            self._pool = ProcessPoolExecutor(
                max_workers=workers,
                mp_context=_context(),
                initializer=_init_worker,
                initargs=(encoder, level),
            )
            self._in_flight = max(1, ahead) * workers
            self._window = 2 * self._in_flight * self.batch
            log.debug("rendering masks with %d worker processes", workers)

    def __enter__(self) -> MaskStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the workers (pending tasks are cancelled)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._futures.clear()
        self._ready.clear()

    def get(self, k: int) -> MaskPair:
        """A fresh ``[left, right]`` PNG list of kept frame ``k``."""
        if k in self._ready:
            return self._ready.pop(k)
        if self._pool is None or k < self._next_collect:
            return list(self.encoder.encode(self.joints[k], self.level))
        while self._next_collect <= k:
            self._fill()
            start, future = self._futures.popleft()
            for i, pair in enumerate(future.result(), start):
                self._ready[i] = list(pair)
            self._next_collect = start + self.batch
            self._fill()
        # frames passed over long ago will not be asked for (or are re-rendered if they are)
        for old in [i for i in self._ready if i < k - self._window]:
            del self._ready[old]
        return self._ready.pop(k)

    def _fill(self) -> None:
        """Keep ``in_flight`` batches submitted."""
        assert self._pool is not None
        n = len(self.joints)
        while len(self._futures) < self._in_flight and self._next_submit < n:
            start = self._next_submit
            chunk = list(self.joints[start : start + self.batch])
            self._futures.append((start, self._pool.submit(_encode_batch, chunk)))
            self._next_submit = start + len(chunk)
