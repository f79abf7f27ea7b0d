"""one_blas_thread: every loaded BLAS runs on one thread inside the block, the previous limits after it."""
import numpy as np
import pytest

from lidar_cam_calib.core import threads
from lidar_cam_calib.core.threads import one_blas_thread


def _blas_threads():
    from threadpoolctl import threadpool_info
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_limits_and_restores():
    pytest.importorskip("threadpoolctl")
    import scipy.linalg  # noqa: F401  (scipy's own BLAS is loaded too)
    from threadpoolctl import threadpool_limits
    assert _blas_threads(), "no BLAS library found among the loaded ones"
    with threadpool_limits(limits=2, user_api="blas"):  # a known state to restore, whatever the machine
        before = _blas_threads()
        with one_blas_thread():
            assert _blas_threads() == [1] * len(before)
            a = np.arange(9.0).reshape(3, 3) + np.eye(3) * 10
            assert np.allclose(np.linalg.solve(a, a @ np.ones(3)), 1.0)  # BLAS still computes
        assert _blas_threads() == before


def test_one_blas_thread_without_threadpoolctl(monkeypatch):
    monkeypatch.setattr(threads, "threadpool_limits", None)
    with one_blas_thread():
        assert np.allclose(np.linalg.inv(np.eye(2) * 2.0), np.eye(2) * 0.5)
