"""Dynamic batching: requests that arrive together are answered by one call, each with its own answer.

    batcher = Batcher(run, max_batch=16, max_wait_s=0.005)   # run(list of items) -> list of answers, in order
    answer = batcher.submit(item).result()                   # from any thread, any transport

One thread takes the first waiting request, waits at most `max_wait_s` for others (up to `max_batch`), and
calls `run` once for them all. A lone request therefore waits `max_wait_s` at most; under load the wait
fills batches instead. Where `run` raises for a batch, each of its requests is run alone, so that one bad
request costs its own answer (its future raises) and not its neighbours'. Knows nothing of networks or
models: the server and the evaluation's shared policy both use it.

`at_fixed_size(run, size)` makes every call one of `size` items, for a `run` whose answers must not depend on
how many requests arrived together (a GPU chooses its kernels by the batch's shape).
"""

import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass


@dataclass
class BatchStats:
    requests: int = 0
    batches: int = 0
    largest: int = 0


_STOP = object()


class Batcher:
    def __init__(self, run, max_batch: int = 16, max_wait_s: float = 0.005, name: str = "batcher"):
        if max_batch < 1 or max_wait_s < 0:
            raise ValueError(f"max_batch {max_batch} must be at least 1 and max_wait_s {max_wait_s} at least 0")
        self.run, self.max_batch, self.max_wait_s = run, max_batch, max_wait_s
        self.stats = BatchStats()
        self._queue: queue.Queue = queue.Queue()
        self._closed = False
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def submit(self, item) -> Future:
        """A future of `item`'s answer; its `batch_size` attribute says how many were answered with it."""
        future: Future = Future()
        with self._lock:
            if self._closed:
                raise RuntimeError("the batcher is closed")
            self._queue.put((item, future))
        return future

    def close(self) -> None:
        """Answer every request already submitted, then stop the thread."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._queue.put(_STOP)
        self._thread.join()

    def _loop(self) -> None:
        while True:
            first = self._queue.get()
            if first is _STOP:
                return
            batch, stop = [first], False
            deadline = time.monotonic() + self.max_wait_s
            while len(batch) < self.max_batch:
                try:
                    entry = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    break
                if entry is _STOP:
                    stop = True
                    break
                batch.append(entry)
            batch = [(item, future) for item, future in batch if future.set_running_or_notify_cancel()]
            if batch:
                self.stats.requests += len(batch)
                self.stats.batches += 1
                self.stats.largest = max(self.stats.largest, len(batch))
                self._answer(batch)
            if stop:
                return

    def _answer(self, batch: list) -> None:
        try:
            answers = self.run([item for item, _ in batch])
            if len(answers) != len(batch):
                raise RuntimeError(f"run answered {len(answers)} of {len(batch)} requests")
        except Exception as error:  # noqa: BLE001 - the requests' futures carry it
            if len(batch) == 1:
                batch[0][1].batch_size = 1
                batch[0][1].set_exception(error)
                return
            for entry in batch:  # each alone: the one that fails fails by itself
                self._answer([entry])
            return
        for (_, future), answer in zip(batch, answers):
            future.batch_size = len(batch)
            future.set_result(answer)


def at_fixed_size(run, size: int):
    """`run` called with exactly `size` items each time: a smaller batch is padded with copies of its first
    item, and only its own answers are returned. A GPU chooses its matrix and attention kernels by the batch's
    shape, so an answer computed among 3 others can differ in its last bits from one computed among 7; at one
    size the kernels are the same whatever arrived together, and each item's answer is computed from its own
    row alone."""
    if size < 1:
        raise ValueError(f"size {size} must be at least 1")

    def padded(items: list) -> list:
        if len(items) > size:
            raise ValueError(f"{len(items)} items for a batch of {size}")
        return run(list(items) + [items[0]] * (size - len(items)))[:len(items)]

    return padded
