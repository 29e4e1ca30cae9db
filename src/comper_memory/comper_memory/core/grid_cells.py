"""GridCells: the geometry of the grid engine (projection, exact cell size, codes, filters).

Why no identity within delta can be missed, with r = sqrt(delta):

* z = P x with P [m, D] having orthonormal rows (m <= 3: PCA directions of the stored keys,
  found inside a random 64-d orthonormal subspace when D > 64), so every coordinate of
  P(x - y) is at most |x - y| (1 + e_o), e_o measured from |P P^T - I|. z is computed in
  float64; its rounding error is below (D + 2) eps64 (|x| + 1) per coordinate, and ``err``
  covers query and stored point.
* Cells are cubes of side c >= (r (1 + e_o) + err)(1 + 1e-7): two points within r have
  cell indices floor((z - o)/c) that differ by at most 1 per axis (the relative rounding of
  the division, < 1e-9 cells, is far below the 1e-7 margin). Indices are clipped to
  [0, 2^21 - 2] (monotone, 1-Lipschitz: neighbours stay neighbours), so c can also be
  made coarse enough for any delta, 0 included.
* A cell's code packs its m indices (21 bits each, lexicographic), so the 3 cells along the
  last axis of each (m-1)-neighbour column are one contiguous code range: a query costs 3^(m-1)
  pairs of ``np.searchsorted`` over the sorted codes (O(log n), vectorised over the batch).
* P has mf >= m rows (``filter_dims``, the largest PCA directions first); the cells use the
  first m coordinates, and a candidate from the neighbour cells is kept only if its float32
  projection lies within the conservative mf-d radius of ``radius_proj`` (|P(x - y)| <=
  |x - y| (1 + e_o) holds for all mf coordinates together). With 3 coordinates, keys that
  vary along many directions (Atari frames) pile up in few cells; 8 coordinates cut the exact
  re-checks on real Freeway transitions from ~24 per stored transition at 5,000 identities to
  ~1 (the re-stores' own identities): benchmarks/memory_atari_bench.py.
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .similarity import SUBSPACE, U32

__all__ = ["GridCells", "GRID_MAX", "NORM_HEADROOM"]

GRID_BITS = 21
# Largest cell index: one below 2^21 - 1, so the largest code (all axes at GRID_MAX) plus one, the
# exclusive end of a code range in a lookup, still fits in int64 (at 2^21 - 1 it wrapped to a
# negative number and queries in the top corner of the grid found nothing).
GRID_MAX = (1 << GRID_BITS) - 2
_EPS64 = float(np.finfo(np.float64).eps)
NORM_HEADROOM = 4.0    # cells are sized for keys up to this many times the largest norm seen
_GRID_HEADROOM = 16.0  # the grid spans this many times the fitted (2nd-98th percentile) extent


class GridCells:
    """Projection P, cell side and origin of the grid, and the exactness bounds that size them."""

    def __init__(self, key_dim: int, delta: float, *, grid_dims: int, filter_dims: int, seed: int):
        self.key_dim = int(key_dim)
        self.r = float(np.sqrt(float(delta)))
        self.m = int(min(grid_dims, self.key_dim, 3))          # cell axes
        self.mf = int(max(self.m, min(filter_dims, self.key_dim, SUBSPACE)))  # filter axes (first m = cells)
        self.seed = int(seed)
        rng = np.random.default_rng(seed)
        q, _ = np.linalg.qr(rng.standard_normal((self.key_dim, self.mf)))
        self.set_projection(np.ascontiguousarray(q.T))
        self.max_key_norm = 0.0
        self.origin: np.ndarray | None = None
        self.cell = np.zeros(self.m)            # side of the cells, per axis
        self.zc0 = np.zeros(self.mf)            # stored projections are fl32(z - zc0)
        sh = [GRID_BITS * (self.m - 1 - d) for d in range(self.m)]
        self._shift = np.asarray(sh, dtype=np.int64)
        offs = np.array(np.meshgrid(*[[-1, 0, 1]] * (self.m - 1), indexing="ij")).reshape(self.m - 1, -1).T \
            if self.m > 1 else np.zeros((1, 0), np.int64)
        self._offs = offs.astype(np.int64)  # [3^(m-1), m-1]

    # ------------------------------------------------------------------ projection
    def set_projection(self, P: np.ndarray) -> None:
        self.P = np.ascontiguousarray(P, dtype=np.float64)
        g = self.P @ self.P.T - np.eye(len(self.P))
        self.e_o = float(np.sqrt((g * g).sum())) + 1e-15

    def fit_directions(self, blocks: Iterable[np.ndarray], rng: np.random.Generator) -> None:
        """New P: the mf largest PCA directions of the sample keys, given as row blocks [k, D].

        Wide keys are projected block by block onto a random SUBSPACE-dimensional subspace first, so
        only that projection of the whole sample is ever held: 20,000 Atari keys of 4 stacked frames
        (D = 56,450) are 4.5 GB as float32 and twice that as float64, their projection 10 MB."""
        if self.key_dim > SUBSPACE:
            q, _ = np.linalg.qr(rng.standard_normal((self.key_dim, SUBSPACE)))
            R = np.ascontiguousarray(q.T)  # [64, D] orthonormal rows
            X = np.concatenate([np.asarray(b, dtype=np.float64) @ R.T for b in blocks])
        else:
            R = None
            X = np.concatenate([np.asarray(b, dtype=np.float64) for b in blocks])
        # robust directions: each column winsorised at its 1st / 99th percentile, so a few
        # outlying keys (one huge value) cannot take over an axis (speed only, never results)
        if len(X) >= 100:
            lo, hi = np.quantile(X, [0.01, 0.99], axis=0)
            np.clip(X, lo, hi, out=X)
        X -= X.mean(axis=0)
        w, V = np.linalg.eigh(X.T @ X)
        top = V[:, np.argsort(w)[::-1][:self.mf]].T  # [mf, d] orthonormal rows, largest first
        self.set_projection(top if R is None else top @ R)

    def observe(self, keys: np.ndarray) -> bool:
        """Track the largest key norm; True if it grew."""
        if not len(keys):
            return False
        nrm = float(np.sqrt(np.einsum("ij,ij->i", keys, keys, dtype=np.float64).max()))
        if nrm > self.max_key_norm:
            self.max_key_norm = nrm
            return True
        return False

    def zproj(self, keys: np.ndarray) -> np.ndarray:
        """float64 P x, in row blocks of ~2 MiB (the float64 copy of a block stays in cache).

        A BLAS product: keep numpy's OpenBLAS at one thread in processes that store (the memory
        node's ``blas_threads``, default 1): with 2 threads this 36 x 14114 by 14114 x 8 product
        took 13-27 ms per store call on the busy 2-core machine instead of 0.7 ms."""
        keys = np.asarray(keys)
        n = len(keys)
        step = max(1, (1 << 18) // max(1, self.key_dim))
        if n <= step:
            return keys.astype(np.float64) @ self.P.T
        z = np.empty((n, len(self.P)))
        PT = self.P.T
        for s in range(0, n, step):
            z[s:s + step] = keys[s:s + step].astype(np.float64) @ PT
        return z

    # ------------------------------------------------------------------ exactness bounds
    def err(self, norm: float | None = None) -> float:
        norm = self.max_key_norm if norm is None else norm
        return 2.0 * (self.key_dim + 2) * _EPS64 * (norm + 1.0) * 4.0

    def min_cell(self, headroom: float = 1.0) -> float:
        """Smallest exact cell side for keys up to ``headroom`` x the largest norm seen. Cells are
        made for 4x the norm (``NORM_HEADROOM``), so keys whose norm keeps growing (drift) force
        a coarser cell (a rebuild) only each time their norm quadruples, not at every store."""
        return (self.r * (1.0 + self.e_o) + self.err(self.max_key_norm * headroom)) * (1.0 + 1e-7) + 1e-300

    def needs_coarser_cell(self) -> bool:
        return self.origin is not None and self.min_cell() > float(self.cell.min())

    def radius_proj(self) -> float:
        """Radius in the mf-d filter space containing every point within r of a query, both in
        float64: |P(x - y)| <= |x - y| (1 + e_o), plus the float64 rounding of z (``err`` per
        coordinate, sqrt(mf) of it in norm, for query and point)."""
        err = self.err() * float(np.sqrt(self.mf))
        return (self.r * (1.0 + self.e_o) + err) * (1.0 + 1e-7)

    def near(self, zq: np.ndarray, zs: np.ndarray) -> np.ndarray:
        """Conservative filter of stored points (never drops a point within r): zq float64
        projections of the queries, zs the stored fl32(z - zc0). The float32 rounding of a stored
        point is at most 2^-24 |z - zc0| per coordinate, so each candidate's radius carries its own
        rounding (a point far from the others, e.g. a huge key value, widens only its own radius)."""
        zs64 = zs.astype(np.float64)
        d = (zq - self.zc0) - zs64
        d2 = np.einsum("ij,ij->i", d, d)
        cast = 2.0 * U32 * (np.sqrt(np.einsum("ij,ij->i", zs64, zs64)) + 1.0)
        rp = self.radius_proj() + cast * (1.0 + 1e-7)
        return d2 <= rp * rp * (1.0 + 1e-9) + 1e-300

    def near64(self, zi: np.ndarray, zj: np.ndarray) -> np.ndarray:
        """The same filter between two float64 projections (pairs inside one batch)."""
        d = zi - zj
        d2 = np.einsum("ij,ij->i", d, d)
        rp = self.radius_proj()
        return d2 <= rp * rp * (1.0 + 1e-9) + 1e-300

    # ------------------------------------------------------------------ cells
    def fit(self, z: np.ndarray) -> None:
        """Per-axis cells over a robust extent: the 2nd-98th percentile range of the points,
        widened _GRID_HEADROOM-fold around its centre (so keys may drift far before they leave
        the grid, and one outlying value cannot stretch the cells); never finer than the
        exactness bound ``min_cell``. Points outside are clipped into the edge cells (still
        exact); the index counts them and re-fits."""
        c = self.min_cell(NORM_HEADROOM)
        if len(z):
            sub = z if len(z) <= 20000 else z[np.random.default_rng(self.seed).choice(
                len(z), 20000, replace=False)]
            zc = sub[:, :self.m]
            lo, hi = np.quantile(zc, [0.02, 0.98], axis=0) if len(zc) >= 16 else (
                zc.min(axis=0), zc.max(axis=0))
            span = np.maximum(hi - lo, 0.0)
            cell = np.maximum(c, span * _GRID_HEADROOM / (GRID_MAX - 4))
            self.origin = (lo + hi) / 2.0 - cell * (GRID_MAX / 2.0)
            self.zc0 = np.median(sub, axis=0)
        else:
            cell = np.full(self.m, c)
            self.origin = -cell * (GRID_MAX / 2.0)
            self.zc0 = np.zeros(self.mf)
        self.cell = cell

    def coarsen(self) -> None:
        """Keep the fitted extent, but make the cells at least the exact side for 4x the norm."""
        self.cell = np.maximum(self.cell, self.min_cell(NORM_HEADROOM))

    def code(self, z: np.ndarray) -> np.ndarray:
        return (self.cells(z) << self._shift).sum(axis=1)

    def raw_cells(self, z: np.ndarray) -> np.ndarray:
        return np.floor((z[:, :self.m] - self.origin) / self.cell)

    def cells(self, z: np.ndarray) -> np.ndarray:
        t = self.raw_cells(z)
        np.clip(t, 0, GRID_MAX, out=t)
        return t.astype(np.int64)

    def ranges(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per query and neighbour column: (lo_code, hi_code, valid) [n, 3^(m-1)]."""
        m = self.m
        last = cells[:, m - 1]
        lo_last = np.maximum(last - 1, 0)[:, None]
        hi_last = np.minimum(last + 1, GRID_MAX)[:, None]
        if m == 1:
            return lo_last, hi_last, np.ones_like(lo_last, dtype=bool)
        head = cells[:, None, :m - 1] + self._offs[None, :, :]       # [n, k, m-1]
        valid = ((head >= 0) & (head <= GRID_MAX)).all(axis=2)
        base = (head << self._shift[None, None, :m - 1]).sum(axis=2)
        return base + lo_last, base + hi_last, valid
