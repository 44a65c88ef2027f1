"""Run the filter's dense updates on a fixed number of BLAS threads.

The covariance updates are O(n^2) matrix products of moderate size (N <= ~1500). On a small or
shared machine a multi-threaded BLAS makes them many times slower, not faster (measured: a
906 x 45 x 906 product took 104 ms on 2 threads of a loaded 2-core machine, 12 ms on one), so
the filter limits BLAS to ``EkfConfig.blas_threads`` around its updates (threadpoolctl, when
installed; ~30 us per call). 0 leaves the library default.
"""

from __future__ import annotations

import contextlib

try:
    from threadpoolctl import ThreadpoolController
except ImportError:  # optional: without it the BLAS default applies
    ThreadpoolController = None

_controller = None


def blas_limit(n_threads: int):
    """Context manager limiting BLAS to ``n_threads`` (no-op for 0 or without threadpoolctl)."""
    global _controller
    if n_threads <= 0 or ThreadpoolController is None:
        return contextlib.nullcontext()
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=n_threads, user_api="blas")
