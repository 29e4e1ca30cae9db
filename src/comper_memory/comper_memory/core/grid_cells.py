"""GridCells: the geometry of the grid engine (projection, exact cell size, codes, filters).

Why no identity within delta can be missed, with r = sqrt(delta):

* z = P x with P [m, D] having orthonormal rows (m <= 3: PCA directions of the stored keys,
  found inside a random 64-d orthonormal subspace when D > 64), so every coordinate of
  P(x - y) is at most |x - y| (1 + e_o), e_o measured from |P P^T - I|. z is computed in
  float64; its rounding error is below (D + 2) eps64 (|x| + 1) per coordinate, and ``err``
  covers query and stored point.
* Cells are cubes of side c >= (r (1 + e_o) + err)(1 + 1e-5): two points within r have
  cell indices t = floor((z - o)/c) that differ by at most 1 per axis (the rounding of the
  division, 4 eps |t| < 7.6e-6 cells while |t| <= 2^33, is below the 1e-5 margin). Indices
  wrap modulo 2^21 - 1 (neighbours stay neighbours modulo it), so keys far outside the fitted
  extent spread over the cells instead of piling up in the edge cells (clipping them put a
  batch that jumped outside the extent into one cell: quadratic in the batch).
* ``err`` grows with the key norm, so the grid takes only keys whose norm is within
  ``norm_cap`` (fixed at each fit: their rounding widens the cells by at most 5 %) and whose
  |t| is at most 2^32 (the wrap is exact); the others ("wide" keys, e.g. one value of 1e20)
  are searched by their norm (``norm_margin``: | |x| - |y| | <= |x - y|), so one huge value
  cannot coarsen the cells of every other key.
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

__all__ = ["GridCells", "GRID_MAX", "NORM_HEADROOM", "PERIOD", "RAW_LIMIT"]

GRID_BITS = 21
# Largest cell index: one below 2^21 - 1, so the largest code (all axes at GRID_MAX) plus one, the
# exclusive end of a code range in a lookup, still fits in int64 (at 2^21 - 1 it wrapped to a
# negative number and queries in the top corner of the grid found nothing).
GRID_MAX = (1 << GRID_BITS) - 2
_EPS64 = float(np.finfo(np.float64).eps)
PERIOD = GRID_MAX + 1  # cell indices wrap modulo this (0 .. GRID_MAX)
NORM_HEADROOM = 4.0    # cells are sized for keys up to this many times the largest norm seen
_GRID_HEADROOM = 16.0  # the grid spans this many times the fitted (2nd-98th percentile) extent
_CELL_MARGIN = 1e-5    # relative cell margin: covers the division's rounding for |t| <= 2^33
RAW_LIMIT = float(1 << 32)  # grid keys have |t| <= this (queries up to 2 more): exact wrap
_SPAN_CELLS = float(1 << 31)  # the fitted extent (x _GRID_HEADROOM) spans at most this many cells
_CAP_ERR = 0.05        # grid keys' rounding (``err``) widens the fitted cells by at most this fraction


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
        self.max_key_norm = 0.0                 # largest norm of the keys the grid takes
        self.norm_cap = float("inf")            # largest norm of a key the grid stores (set by fit)
        self.origin: np.ndarray | None = None
        self.cell = np.zeros(self.m)            # side of the cells, per axis
        self.ext_lo = self.ext_hi = np.zeros(self.m)  # the fitted extent (z of the cell axes)
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

    @staticmethod
    def norms(keys: np.ndarray) -> np.ndarray:
        """float64 norms |x| of float32 keys [n, D] (rows of 2 MiB at a time for wide keys)."""
        keys = np.asarray(keys)
        n = len(keys)
        out = np.empty(n)
        step = max(1, (1 << 18) // max(1, keys.shape[1] if keys.ndim == 2 else 1))
        for s in range(0, n, step):
            k = keys[s:s + step].astype(np.float64)
            out[s:s + step] = np.sqrt(np.einsum("ij,ij->i", k, k))
        return out

    def norm_margin(self, norm) -> np.ndarray | float:
        """Largest difference of computed norms of two keys within r, for keys of norm up to
        ``norm``: r, plus the float64 rounding of both norms ((D/2 + 1) eps |x| each, taken 4x)."""
        return self.r * (1.0 + 1e-6) + 4.0 * (self.key_dim + 3) * _EPS64 * (np.asarray(norm) + self.r + 1.0)

    def observe(self, norms: np.ndarray) -> bool:
        """Track the largest norm of the keys the grid takes (``grid_query``); True if it grew."""
        if not len(norms):
            return False
        nrm = float(np.max(norms))
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
        return (self.r * (1.0 + self.e_o) + self.err(self.max_key_norm * headroom)) * (1.0 + _CELL_MARGIN) + 1e-300

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

    def near64(self, zi: np.ndarray, zj: np.ndarray, norm: np.ndarray | None = None) -> np.ndarray:
        """The same filter between two float64 projections (pairs inside one batch; wide keys).
        norm: per pair, the larger norm of the two keys (wide keys: their own rounding bound);
        None: grid keys (``radius_proj``)."""
        d = zi - zj
        d2 = np.einsum("ij,ij->i", d, d)
        if norm is None:
            rp = self.radius_proj()
        else:
            err = 2.0 * (self.key_dim + 2) * _EPS64 * (np.asarray(norm) + self.r + 1.0) * 4.0
            rp = (self.r * (1.0 + self.e_o) + err * float(np.sqrt(self.mf))) * (1.0 + 1e-7)
        return d2 <= rp * rp * (1.0 + 1e-9) + 1e-300

    # ------------------------------------------------------------------ cells
    def fit(self, z: np.ndarray, norms: np.ndarray) -> None:
        """Per-axis cells over a robust extent: the 2nd-98th percentile range of the points,
        widened _GRID_HEADROOM-fold around its centre (so keys may drift far before they leave
        the grid, and one outlying value cannot stretch the cells); never finer than the
        exactness bound ``min_cell``. Points outside wrap around (still exact); the index counts
        them and re-fits. ``norm_cap``: the largest norm whose rounding widens these cells by at
        most _CAP_ERR; the cells are sized for the largest norm up to it (norms: the points' |x|)."""
        rcell = np.full(self.m, self.r * (1.0 + self.e_o) * (1.0 + _CELL_MARGIN))
        span = np.zeros(self.m)
        centre = np.zeros(self.m)
        if len(z):
            sub = z if len(z) <= 20000 else z[np.random.default_rng(self.seed).choice(
                len(z), 20000, replace=False)]
            zc = sub[:, :self.m]
            lo, hi = np.quantile(zc, [0.02, 0.98], axis=0) if len(zc) >= 16 else (
                zc.min(axis=0), zc.max(axis=0))
            span = np.maximum(hi - lo, 0.0)
            centre = (lo + hi) / 2.0
        # the grid's keys' rounding widens the cells by at most _CAP_ERR of a cell that spans the
        # extent in 2^21 (r at least): err(NORM_HEADROOM * cap) <= _CAP_ERR * that cell
        per_norm = 2.0 * (self.key_dim + 2) * _EPS64 * 4.0 * NORM_HEADROOM
        coarse = np.maximum(rcell, span * _GRID_HEADROOM / (GRID_MAX - 4))
        self.norm_cap = max(0.0, _CAP_ERR * float(coarse.min()) / per_norm - 1.0)
        norms = np.asarray(norms, dtype=np.float64)
        self.observe(norms[norms <= self.norm_cap + self.norm_margin(2.0 * self.norm_cap + 1.0)])
        # cells: the exact side, or finer than the extent needs only when the extent spans
        # more than 2^30 of them (keys _GRID_HEADROOM / 2 extents away then still wrap exactly)
        cell = np.maximum(np.maximum(rcell, span * _GRID_HEADROOM / _SPAN_CELLS), self.min_cell(NORM_HEADROOM))
        half = np.maximum(span * (_GRID_HEADROOM / 2.0), cell * (GRID_MAX / 2.0))
        self.ext_lo, self.ext_hi = centre - half, centre + half
        self.origin = centre - cell * (GRID_MAX / 2.0)
        self.zc0 = np.median(sub, axis=0) if len(z) else np.zeros(self.mf)
        self.cell = cell

    def outside(self, z: np.ndarray) -> np.ndarray:
        """bool [n]: points outside the fitted extent (the index re-fits once they are many)."""
        zc = z[:, :self.m]
        return ((zc < self.ext_lo) | (zc > self.ext_hi)).any(axis=1)

    def reach(self, z: np.ndarray) -> np.ndarray:
        """max over the cell axes of |t|, t = (z - o) / c (the unwrapped cell index), per point."""
        if not len(z):
            return np.zeros(0)
        return np.abs((z[:, :self.m] - self.origin) / self.cell).max(axis=1)

    def grid_store(self, z: np.ndarray, norms: np.ndarray) -> np.ndarray:
        """bool [n]: which points the grid stores (the others are wide keys)."""
        return (norms <= self.norm_cap) & (self.reach(z) <= RAW_LIMIT)

    def grid_query(self, z: np.ndarray, norms: np.ndarray) -> np.ndarray:
        """bool [n]: which queries may have a grid key within r (and have exact wrapped cells):
        a key within r of a grid key has a norm within ``norm_margin`` and a |t| within 1 + 1e-5."""
        cap = self.norm_cap
        return (norms <= cap + self.norm_margin(2.0 * cap + 1.0)) & (self.reach(z) <= RAW_LIMIT + 2.0)

    def wide_query(self, z: np.ndarray, norms: np.ndarray) -> np.ndarray:
        """bool [n]: which batch items may be within r of a wide key (pairs inside a batch)."""
        cap = self.norm_cap
        return (norms > cap - self.norm_margin(2.0 * cap + 1.0)) | (self.reach(z) > RAW_LIMIT - 2.0)

    def coarsen(self) -> None:
        """Keep the fitted extent, but make the cells at least the exact side for 4x the norm."""
        self.cell = np.maximum(self.cell, self.min_cell(NORM_HEADROOM))

    def code(self, z: np.ndarray) -> np.ndarray:
        return (self.cells(z) << self._shift).sum(axis=1)

    def raw_cells(self, z: np.ndarray) -> np.ndarray:
        return np.floor((z[:, :self.m] - self.origin) / self.cell)

    def cells(self, z: np.ndarray) -> np.ndarray:
        """Cell indices wrapped modulo PERIOD (points with ``reach`` <= RAW_LIMIT + 2 only)."""
        t = self.raw_cells(z)
        np.clip(t, -2.0 ** 52, 2.0 ** 52, out=t)   # finite int64 for any input; exact below 2^33
        return np.mod(t.astype(np.int64), PERIOD)

    def ranges(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per query and neighbour column: (lo_code, hi_code, valid) [n, k]: k = 3^(m-1) code
        ranges (the 3 cells along the last axis of each neighbour column, wrapped head indices),
        and 3^(m-1) more when a query's last index is at either end (the neighbour that wraps
        to the other end of the last axis; valid only for those queries)."""
        m = self.m
        last = cells[:, m - 1]
        lo_last = np.maximum(last - 1, 0)[:, None]
        hi_last = np.minimum(last + 1, GRID_MAX)[:, None]
        edge = (last == 0) | (last == GRID_MAX)
        if m == 1:
            base = np.zeros((len(cells), 1), np.int64)
        else:
            head = np.mod(cells[:, None, :m - 1] + self._offs[None, :, :], PERIOD)  # [n, k, m-1]
            base = (head << self._shift[None, None, :m - 1]).sum(axis=2)
        lo, hi = base + lo_last, base + hi_last
        valid = np.ones(lo.shape, dtype=bool)
        if edge.any():
            w = np.where(last == 0, GRID_MAX, 0)[:, None]   # the wrapped neighbour on the last axis
            lo = np.concatenate([lo, base + w], axis=1)
            hi = np.concatenate([hi, base + w], axis=1)
            valid = np.concatenate([valid, np.repeat(edge[:, None], base.shape[1], axis=1)], axis=1)
        return lo, hi, valid
