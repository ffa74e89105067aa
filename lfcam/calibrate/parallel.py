"""Threads for the calibration's large array loops.

The white-image calibration is numpy and OpenCV work on large float32 arrays (per-lens patch
blocks, image row bands). Those operations release the GIL, so a few threads share the work
without copying the image: :func:`run_chunks` runs a function over consecutive slices of a
lens list, :func:`run_bands` over row bands of an image. The callers write only their own
slice or band of shared output arrays (or hold a lock), so the result does not depend on the
number of threads.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

MAX_THREADS = 4


def worker_threads() -> int:
    """Threads to use: the cores this process may run on, at most ``MAX_THREADS``.

    The environment variable ``LFCAM_THREADS`` overrides it (1 = serial).
    """
    env = os.environ.get("LFCAM_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(MAX_THREADS, cores))


def run_chunks(fn: Callable[[slice], object], n: int, chunk: int) -> list:
    """``fn(slice)`` for consecutive slices of ``range(n)`` of length ``chunk``, on
    :func:`worker_threads` threads; the results in slice order."""
    slices = [slice(s, min(n, s + chunk)) for s in range(0, n, chunk)]
    threads = min(worker_threads(), len(slices))
    if threads <= 1:
        return [fn(sl) for sl in slices]
    with ThreadPoolExecutor(threads) as ex:
        return list(ex.map(fn, slices))


def run_bands(fn: Callable[[int, int], object], height: int, min_rows: int = 256,
              max_rows: int | None = None) -> list:
    """``fn(r0, r1)`` for row bands ``[r0, r1)`` covering ``range(height)`` (two per thread,
    at least ``min_rows`` rows each, and with ``max_rows`` at most that many: more bands
    than threads), on :func:`worker_threads` threads; results in band order.

    ``max_rows`` keeps a band's temporaries small enough for the allocator to reuse them from
    one band to the next: a fresh array of tens of MB pays a page fault per page on first
    touch (on a 41 Mpx white, ~0.2 s of CPU per full-size array on this project's machines).
    """
    threads = worker_threads()
    bands = max(1, min(2 * threads, height // max(1, min_rows)))
    if max_rows:
        bands = max(bands, -(-height // max_rows))
    edges = [round(i * height / bands) for i in range(bands + 1)]
    pairs = list(zip(edges[:-1], edges[1:], strict=True))
    if threads <= 1 or bands == 1:
        return [fn(a, b) for a, b in pairs]
    with ThreadPoolExecutor(min(threads, bands)) as ex:
        return list(ex.map(lambda ab: fn(*ab), pairs))
