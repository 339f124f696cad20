"""Launching per-pixel kernels on all CPU cores.

Warp runs a CPU launch on one thread. Per-pixel kernels that take a ``row0`` offset
can instead be launched over bands of image rows from several Python threads: Warp's
CPU kernels keep no global state and ctypes releases the GIL during the launch. On
CUDA a single launch covers all rows.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor, wait

import numpy as np

# A few bands per worker so that rows of uneven cost balance out.
_BANDS_PER_WORKER = 4
_pool: ThreadPoolExecutor | None = None


def cpu_workers() -> int:
    """CPU threads used for per-pixel kernels: ``MCGS_WARP_CPU_THREADS`` or the core count."""
    return max(1, int(os.environ.get("MCGS_WARP_CPU_THREADS", os.cpu_count() or 1)))


def band_workers(device, height: int) -> int:
    """Workers :func:`run_row_bands` uses for ``height`` rows: 1 on CUDA, else at most one
    per CPU thread and per row (callers size per-worker accumulators with it)."""
    return 1 if device.is_cuda else min(cpu_workers(), max(1, height))


def run_row_bands(device, height: int, launch_band) -> int:
    """Call ``launch_band(worker, row0, rows)`` over bands of image rows. On CUDA one call
    covers all rows; on the CPU worker ``w`` runs bands ``w, w + workers, ...`` in order.
    Returns the number of workers used."""
    global _pool
    workers = band_workers(device, height)
    if workers == 1:
        launch_band(0, 0, height)
        return 1
    edges = np.linspace(0, height, workers * _BANDS_PER_WORKER + 1).astype(int)
    bands = [(int(a), int(b - a)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    if _pool is None or _pool._max_workers < workers:
        _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mcgs-warp")

    def work(w):
        for row0, rows in bands[w::workers]:
            launch_band(w, row0, rows)

    futures = [_pool.submit(work, w) for w in range(1, workers)]
    try:
        work(0)  # the calling thread takes worker 0's bands: one hand-off fewer
    finally:
        wait(futures)  # never return (or raise) while a worker still writes
    for f in futures:
        f.result()  # a worker's error, if any
    return workers
