"""fbgcomp.threads with the real threadpoolctl and the process's own OpenBLAS pools."""

import numpy as np

import fbgcomp_testing
from fbgcomp.threads import one_blas_thread


def _blas_threads():
    from threadpoolctl import threadpool_info

    return sorted((p["filepath"], p["num_threads"]) for p in threadpool_info() if p["user_api"] == "blas")


def test_one_blas_thread_limits_every_blas_pool_and_restores_it():
    fbgcomp_testing.require("threadpoolctl")
    import scipy.linalg  # noqa: F401 - SciPy's own OpenBLAS, as the twin's factorisations load it
    from threadpoolctl import threadpool_limits

    with threadpool_limits(2):  # whatever the environment set, two threads to begin with
        before = _blas_threads()
        assert before and all(n == 2 for _, n in before), before
        for _ in range(2):  # the pools are listed once; every entry limits and restores them
            with one_blas_thread():
                inside = _blas_threads()
                x = np.linalg.solve(np.eye(3) * 2.0, np.ones(3))
            assert [f for f, _ in inside] == [f for f, _ in before]
            assert all(n == 1 for _, n in inside), inside
            assert _blas_threads() == before
        np.testing.assert_array_equal(x, 0.5)
