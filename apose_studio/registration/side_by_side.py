"""Independent estimates run side by side on threads, their results taken in the order a sequential loop
would take them, so the answer is the same on any number of threads.

The mask's readings (pipeline.estimate_readings) are up to four full estimates, each a pure function of the
frame and its own mask: on the real-like captures (benchmarks/captures.py `stacked`, `hidden`, `real`) they
are 50-75 % of a frame's time. Their numpy steps, k-d tree queries and ray casts release Python's lock for part
of their work, so two of them on two cores take about a sixth less time than one after the other (docs/BENCHMARKS.md:
1.2x on two cores; their many small steps take turns on the lock, the rest runs side by side). Whatever is
shared between them is built once under a lock and never changed after (the base's ray casts and trees,
`registration.base`) or drawn under one (Open3D's seeded RANSAC, `stages.global_registration`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

from apose_studio import safeio
from apose_studio.geometry.nn import usable_cpus  # (the k-d tree's own thread count reads it too)

T = TypeVar("T")
R = TypeVar("R")


class Abandoned(Exception):
    """Raised by `check` in a worker whose result the caller no longer wants (it found what it looked for)."""


_WORKER = threading.local()  # .stop: the Event of the `in_order` call this thread works for


def check() -> None:
    """Raise Abandoned when this thread computes an item ahead for an `in_order` call that has ended. The long
    loops call it (each ICP step, each ray cast): a reading computed ahead of the one that settled the frame stops
    within about a millisecond instead of running on for a quarter of a second that the caller would wait for.
    Nothing when called outside such a worker."""
    stop = getattr(_WORKER, "stop", None)
    if stop is not None and stop.is_set():
        raise Abandoned


@contextmanager
def in_order(fn: Callable[[T], R], items: Sequence[T], threads: int) -> Iterator[Iterator[R]]:
    """`fn` of each item, yielded in the items' order. With `threads` > 1 (at most the usable CPUs), the first
    item is computed alone in the caller's thread, and once the caller asks for the second the rest are computed
    ahead on a pool of `threads` while the caller looks at them in order; leaving the `with`
    early (a caller that found what it looked for) cancels what has not started, stops what has at its next
    `check` and waits for it, so no work outlives the call. An exception in `fn` is raised where its item is
    reached, as in a loop. A worker reads files only where its caller may (`safeio.reads_within`)."""
    threads = min(threads, usable_cpus(), len(items) - 1)  # (the first item is the caller's own)
    if threads <= 1:
        yield (fn(item) for item in items)
        return
    results = _first_alone(fn, items, threads)
    try:
        yield results
    finally:
        results.close()  # leaving the `with`: the pool, if started, stops now, not when the caller's frame ends


def _first_alone(fn: Callable[[T], R], items: Sequence[T], threads: int) -> Iterator[R]:
    """The first item in the caller's thread, alone; the rest side by side only once the caller asks for the second.
    The first reading of a mask is the one that settles a frame most often, and computed beside another it would
    share the cores with it: on 10 `hidden` frames that end at their first reading, starting both at once made them
    23 % slower (docs/BENCHMARKS.md)."""
    yield fn(items[0])
    with _ahead(fn, items[1:], threads) as rest:
        yield from rest


@contextmanager
def _ahead(fn: Callable[[T], R], items: Sequence[T], threads: int) -> Iterator[Iterator[R]]:
    """`fn` of each item on a pool of `threads`, yielded in order; leaving early stops the rest (`in_order`)."""
    stop = threading.Event()
    roots = safeio.read_roots()  # the caller's confinement (the studio's workspace) holds in its workers too

    def work(item: T) -> R:
        _WORKER.stop = stop
        try:
            with safeio.reads_within(roots):
                return fn(item)
        finally:
            _WORKER.stop = None

    with ThreadPoolExecutor(threads, thread_name_prefix="apose-side-by-side") as pool:
        futures = [pool.submit(work, item) for item in items]
        try:
            yield (f.result() for f in futures)
        finally:
            stop.set()
            for f in futures:
                f.cancel()
