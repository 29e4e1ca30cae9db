"""Thread count of the BLAS library numpy is linked with (OpenBLAS in the numpy wheels).

numpy's OpenBLAS starts one thread per core for a matrix product as small as the memory's key
projection (36 x 14114 by 14114 x 8). On the 2-core machine, where the learner and the QT
trainer already keep both cores busy, those threads wait for each other: the projection took
13-27 ms per store call with the default threads and 0.7 ms with one (benchmarks/
memory_atari_bench.py, docs/memory.md). torch's threads are separate (``torch.set_num_threads``).

Setting the count at run time (instead of OPENBLAS_NUM_THREADS before numpy is imported) lets a
node apply its parameter whatever was imported first. Pure ctypes, no new dependency: the
library is found among the process's mapped files.
"""
from __future__ import annotations

import ctypes

__all__ = ["set_numpy_blas_threads"]

_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
            "openblas_set_num_threads64_", "openblas_set_num_threads")
_GETTERS = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads",
            "openblas_get_num_threads64_", "openblas_get_num_threads")


def _openblas_libraries() -> list[str]:
    import numpy  # noqa: F401  (the library is mapped once numpy is imported)
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower() and "/" in line}
    except OSError:  # not Linux: leave the library's default
        return []
    return sorted(paths)


def set_numpy_blas_threads(n: int) -> int | None:
    """Set numpy's OpenBLAS thread count to ``n`` (>= 1) for the whole process.

    Returns the count in effect afterwards, or None when no OpenBLAS library with a known
    setter is loaded (another BLAS, another OS): then nothing changed."""
    if int(n) < 1:
        raise ValueError(f"BLAS threads must be >= 1, got {n}")
    result = None
    for path in _openblas_libraries():
        lib = ctypes.CDLL(path)
        setter = next((getattr(lib, s) for s in _SETTERS if hasattr(lib, s)), None)
        getter = next((getattr(lib, s) for s in _GETTERS if hasattr(lib, s)), None)
        if setter is None:
            continue
        setter.argtypes = [ctypes.c_int]
        setter.restype = None
        setter(int(n))
        if getter is not None:
            getter.restype = ctypes.c_int
            result = int(getter())
        else:
            result = int(n)
    return result
