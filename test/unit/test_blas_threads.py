"""numpy's OpenBLAS thread count, set at run time (comper_msgs_py.blas)."""
import numpy as np
import pytest

from comper_msgs_py.blas import set_numpy_blas_threads


def test_set_numpy_blas_threads_takes_effect_and_products_stay_equal():
    a = np.random.default_rng(0).random((36, 2000))
    p = np.random.default_rng(1).random((2000, 8))
    before = a @ p
    assert set_numpy_blas_threads(2) == 2   # the numpy wheels ship OpenBLAS
    assert set_numpy_blas_threads(1) == 1
    np.testing.assert_allclose(a @ p, before, rtol=1e-12)


def test_set_numpy_blas_threads_refuses_zero():
    with pytest.raises(ValueError, match=">= 1"):
        set_numpy_blas_threads(0)
