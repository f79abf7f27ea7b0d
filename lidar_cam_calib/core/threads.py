"""BLAS threads during a calibration (ROS-free).

numpy, scipy and OpenCV each load their own OpenBLAS, and each starts one
thread per core. The calibrators' linear algebra is small (3x3 to 100x100
solves, thin N x 3 products), too small for threads to pay, yet an OpenBLAS
thread that finished its share spins waiting for the next call: on 2 cores
it takes the core that the other half of the work (the target-less method's
LiDAR side, OpenCV's own threads, the kd-tree queries) runs on. Measured on
a simulated HDL-64 window (``targetless``): 53 s of CPU for 31 s of wall time
with OpenBLAS's default, 40 s for 28.5 s with one BLAS thread, the same
estimate to 1e-12 (only the order of the sums changes).

:func:`one_blas_thread` limits every loaded BLAS to one thread for the span
of a ``with`` block, through ``threadpoolctl`` (it finds each library's own
setter). Without ``threadpoolctl`` the block changes nothing.
"""
from __future__ import annotations

import contextlib

try:
    from threadpoolctl import threadpool_limits
except ImportError:  # optional: the calibration is the same, only slower on few cores
    threadpool_limits = None


def one_blas_thread():
    """A context manager: one BLAS thread inside the block (the previous limits are restored on exit).
    The limit is process-wide while the block runs, so threads started inside it share it."""
    if threadpool_limits is None:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


__all__ = ["one_blas_thread"]
