"""Batches for training and evaluation: per-epoch shuffling, a shard per process, background
prefetch and an exact, checkpointable position.

`Loader` is epoch based: `for batch in loader` runs the rest of the current epoch and then moves
the position to the start of the next one, so

    for epoch in range(num_epochs):
        for batch in loader:
            ...

trains num_epochs epochs, and after `loader.set_state(saved)` the same loop continues with the
exact batch the saved run would have produced next.

Order: epoch e visits `indices` in the permutation `default_rng((seed, e)).permutation`
(or in the given order with shuffle=False). The epoch's list is read as global batches
of `batch_size` x process_count examples, and process p takes the p-th block of `batch_size` of
each: the rows that one process holding every device would place on process p's devices, so a
multi-host run trains on the same device batches (and BatchNorm groups) as one process with the
same devices. drop_remainder=True drops the examples past the last full global batch;
drop_remainder=False pads the last global batch with copies of the epoch's first example and the
batch's `mask` marks the real ones, so every batch has the same shapes and each example of the
epoch is seen exactly once with mask True. The shards are disjoint and together cover the epoch.

Augmentation (augment=True) draws from `default_rng((seed, epoch, index))`, index being the
dataset index of the sample: the same sample gets the same augmentation in the same epoch
whatever the process count, batch size or resume point.

A plain loader of our own rather than grain: the state is two integers, the shard rule is the
one above, and the prefetch thread is a queue; grain's MapDataset would add workers we do not
need at these sizes. Reading uses a small thread pool (OpenCV's PNG decoding releases the GIL).
"""

from __future__ import annotations

import concurrent.futures
import queue
import threading
from typing import Callable, Iterator

import numpy as np

from irdepth_jax.data.augment import augment as augment_sample


def _stack(samples: list[dict]) -> dict:
    keys = samples[0].keys()
    for s in samples[1:]:
        if s.keys() != keys:
            raise ValueError(f"samples have different keys: {sorted(keys)} vs {sorted(s.keys())}")
    out = {}
    for k in keys:
        values = [s[k] for s in samples]
        if isinstance(values[0], str):
            out[k] = np.array(values, dtype=str)
        else:
            shapes = {np.shape(v) for v in values}
            if len(shapes) != 1:
                raise ValueError(
                    f"key {k!r}: samples of different shapes {sorted(shapes)}; resize first")
            out[k] = np.stack([np.asarray(v) for v in values])
    return out


class Loader:
    """Sharded, shuffled, prefetching batch iterator over a dataset with `__getitem__(i)`.

    Args:
      dataset: object with `__getitem__(i) -> dict` (FolderDataset, MS2Dataset, a list of dicts).
      indices: the dataset indices to iterate (e.g. `dataset.indices(split='train')`).
      batch_size: examples per batch on this process.
      seed: shuffling / augmentation seed.
      shuffle: permute the indices each epoch.
      drop_remainder: drop the incomplete tail (True) or pad it and mark it in `mask` (False).
      augment: apply `irdepth_jax.data.augment.augment` (or a callable(sample, rng) -> sample).
      process_index, process_count: this process's shard; default jax.process_index() /
        jax.process_count().
      prefetch: batches prepared ahead in a background thread (0 = none).
      num_threads: threads reading samples in parallel.

    Batches are dicts of numpy arrays stacked on a leading batch axis (strings as a numpy str
    array) plus `index` (B,) int64 dataset indices and `mask` (B,) bool.
    """

    def __init__(self, dataset, indices, batch_size: int, seed: int = 0, shuffle: bool = True,
                 drop_remainder: bool = True, augment: bool | Callable = False,
                 process_index: int | None = None, process_count: int | None = None,
                 prefetch: int = 2, num_threads: int = 2):
        if process_index is None or process_count is None:
            import jax

            process_index = jax.process_index() if process_index is None else process_index
            process_count = jax.process_count() if process_count is None else process_count
        if not 0 <= process_index < process_count:
            raise ValueError(
                f"process_index {process_index} not in [0, process_count={process_count})")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.dataset = dataset
        self.indices = np.asarray(indices, np.int64).reshape(-1)
        self.batch_size = batch_size
        self.seed = int(seed)
        self.shuffle = shuffle
        self.drop_remainder = drop_remainder
        self.augment = augment_sample if augment is True else (augment or None)
        self.process_index, self.process_count = process_index, process_count
        self.prefetch = prefetch
        self.num_threads = max(1, num_threads)
        n = len(self.indices)
        per_proc = n // process_count if drop_remainder else -(-n // process_count)
        self._per_proc = per_proc
        self.batches_per_epoch = (per_proc // batch_size if drop_remainder
                                  else -(-per_proc // batch_size))
        if self.batches_per_epoch == 0:
            raise ValueError(f"{n} examples over {process_count} processes give no batch of "
                             f"{batch_size} (drop_remainder={drop_remainder})")
        self.epoch, self.index = 0, 0

    def __len__(self) -> int:
        return self.batches_per_epoch

    # --- position
    def get_state(self) -> dict:
        """JSON-able position: the next batch is batch `index` of epoch `epoch`."""
        return dict(epoch=self.epoch, index=self.index, seed=self.seed,
                    num_examples=len(self.indices), process_count=self.process_count,
                    batch_size=self.batch_size)

    def set_state(self, state: dict) -> None:
        """Restores a position saved by `get_state` (same seed, data, batch size, process count)."""
        for key in ("seed", "num_examples", "process_count", "batch_size"):
            mine = self.get_state()[key]
            if key in state and state[key] != mine:
                raise ValueError(f"loader state has {key}={state[key]}, this loader has {mine}")
        epoch, index = int(state["epoch"]), int(state["index"])
        if epoch < 0 or not 0 <= index <= self.batches_per_epoch:
            raise ValueError(f"loader state epoch={epoch} index={index} out of range "
                             f"(batches per epoch {self.batches_per_epoch})")
        self.epoch, self.index = epoch, index
        if index == self.batches_per_epoch:
            self.epoch, self.index = epoch + 1, 0

    # --- order
    def epoch_shard(self, epoch: int) -> tuple[np.ndarray, np.ndarray]:
        """(indices, mask) of this process for `epoch`, length batches_per_epoch * batch_size."""
        order = self.indices
        if self.shuffle:
            order = np.random.default_rng((self.seed, epoch)).permutation(order)
        n, p, b = len(order), self.process_count, self.batch_size
        total = self.batches_per_epoch * b  # this process's share
        mask = np.ones(n, bool)
        if n < total * p:  # pad the last global batch (drop_remainder=False) ...
            pad = total * p - n
            order = np.concatenate([order, np.repeat(order[:1], pad)])
            mask = np.r_[mask, np.zeros(pad, bool)]
        # ... or drop the examples past the last full one; then each global batch of b * p
        # examples gives process i its i-th block of b (the rows one process with all the
        # devices would place on them)
        rows = np.arange(total * p).reshape(self.batches_per_epoch, p, b)[:, self.process_index]
        shard, shard_mask = order[rows.ravel()], mask[rows.ravel()]
        return shard[:total], shard_mask[:total]

    def _load(self, epoch: int, index: int) -> dict:
        sample = self.dataset[int(index)]
        if self.augment is not None:
            sample = self.augment(sample, np.random.default_rng((self.seed, epoch, int(index))))
        return sample

    def _batches(self, epoch: int, start: int, pool) -> Iterator[dict]:
        shard, mask = self.epoch_shard(epoch)
        for b in range(start, self.batches_per_epoch):
            sl = slice(b * self.batch_size, (b + 1) * self.batch_size)
            samples = list(pool.map(lambda i: self._load(epoch, i), shard[sl]))
            batch = _stack(samples)
            batch["index"], batch["mask"] = shard[sl].copy(), mask[sl].copy()
            yield batch

    # --- iteration
    def __iter__(self) -> Iterator[dict]:
        """Yields the remaining batches of the current epoch, then advances to the next epoch."""
        if self.index >= self.batches_per_epoch:  # stopped right after an epoch's last batch
            self.epoch, self.index = self.epoch + 1, 0
        epoch, start = self.epoch, self.index
        with concurrent.futures.ThreadPoolExecutor(self.num_threads) as pool:
            source = self._batches(epoch, start, pool)
            if self.prefetch > 0:
                source = prefetch(source, self.prefetch)
            try:
                for batch in source:
                    self.index += 1
                    yield batch
            finally:  # also when the consumer stops early: ends the prefetch thread
                source.close()
        if self.index >= self.batches_per_epoch:
            self.epoch, self.index = epoch + 1, 0


def prefetch(source: Iterator, depth: int, name: str = "loader-prefetch") -> Iterator:
    """Runs `source` in a daemon thread `name`, at most `depth` items ahead; errors re-raise in
    the consumer; the thread never blocks once the consumer has stopped."""
    q: queue.Queue = queue.Queue(maxsize=max(depth, 1))
    stop = threading.Event()
    done = object()

    def put(item) -> bool:  # False once the consumer has gone
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for item in source:
                if not put(item):
                    return
            put(done)
        except BaseException as e:  # handed to the consumer
            put(e)

    thread = threading.Thread(target=work, daemon=True, name=name)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join(timeout=5)
