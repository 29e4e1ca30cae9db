"""The grid engine of the similarity index: identities in sorted cell codes (numpy only).

It proposes candidates only; :class:`~comper_memory.core.similarity.SimilarityIndex` re-checks
every candidate that is still alive against its full key in float64 and decides. The cells and
why they miss no identity within delta are in :mod:`~comper_memory.core.grid_cells`.

Storage: two sorted levels (code int64, id int64, projection mf float32): a large main level
and a small level that new identities are inserted into (``np.insert``, O(small)); the small
level is merged into the main one when it exceeds main/16 (amortised O(1) per identity).
Removal is lazy: evicted ids stay as stale entries (ids are never reused, and candidates are
filtered with the key source's ``alive``) until a rebuild, which happens when stale entries
exceed a quarter of the entries, when identities grew ``rebuild_growth``-fold since the last
build (re-fitting the PCA directions and the grid extent), or when a key's norm would need a
coarser cell.
"""
from __future__ import annotations

import numpy as np

from .grid_cells import GRID_MAX, GridCells
from .similarity import KeySource, SimilarityIndex

__all__ = ["GridIndex"]

_PAIR_CHUNK = 1 << 21  # candidate pairs expanded at once (bounds temporary memory)
_KEY_BLOCK = 1 << 22  # key values per block when every live key is read (rebuild, re-fit)


def _expand(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, position) for every position in [lo[r], hi[r]) of every row r (vectorised)."""
    cnt = np.maximum(hi - lo, 0).ravel()
    tot = int(cnt.sum())
    if tot == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    row = np.repeat(np.arange(len(cnt)), cnt)
    start = np.cumsum(cnt) - cnt
    pos = np.repeat(lo.ravel() - start, cnt) + np.arange(tot)
    return row, pos


def _lookup(levels, lo_code, hi_code, valid):
    """[(lo, hi)] position ranges in each sorted code array of ``levels``."""
    # needles searched in increasing order (numpy's binary search then reuses its bounds)
    needles = np.concatenate([lo_code.ravel(), hi_code.ravel() + 1])  # side=right == left of +1
    o = np.argsort(needles)
    sn = needles[o]
    k = lo_code.size
    out = []
    for codes_sorted in levels:
        pos = np.empty(len(needles), np.int64)
        pos[o] = np.searchsorted(codes_sorted, sn, side="left")
        lo = pos[:k].reshape(lo_code.shape)
        hi = pos[k:].reshape(lo_code.shape)
        out.append((lo, np.where(valid, hi, lo)))
    return out


def _query_chunks(cnt: np.ndarray):
    """Split queries into chunks whose expanded candidate count stays bounded."""
    n = len(cnt)
    if n == 0:
        return
    cum = np.cumsum(cnt)
    s = 0
    while s < n:
        base = cum[s - 1] if s else 0
        e = int(np.searchsorted(cum, base + _PAIR_CHUNK, side="right"))
        e = max(e, s + 1)
        yield s, min(e, n)
        s = e


class GridIndex(SimilarityIndex):
    """Exact radius-delta index over a sorted-cell-code grid (see module docstring)."""

    engine = "grid"

    def __init__(self, key_dim: int, delta: float, source: KeySource, *, grid_dims: int = 3,
                 filter_dims: int = 8, min_train: int = 2048, rebuild_growth: float = 4.0, seed: int = 0):
        super().__init__(key_dim, delta, source)
        self.grid = GridCells(key_dim, delta, grid_dims=grid_dims, filter_dims=filter_dims, seed=seed)
        self.mf = self.grid.mf
        self.min_train = int(min_train)
        self.rebuild_growth = float(rebuild_growth)
        self.seed = int(seed)
        self.clipped = 0                        # identities added outside the grid since the last build
        self.scanned = 0                        # candidate pairs taken from neighbour cells (cost counter)
        self.codes = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self.zs = np.zeros((0, self.mf), np.float32)
        self._clear_small()
        self.stale = 0
        self.n_at_build = 0
        self.rebuilds = 0

    @property
    def ntotal(self) -> int:
        return int(len(self.codes) + len(self.scodes) - self.stale)

    @property
    def nlist(self) -> int:
        """Occupied grid cells (the partition's size; tests and benchmarks report it)."""
        c = np.concatenate([self.codes, self.scodes])
        return int(len(np.unique(c))) if len(c) else 0

    def bytes_used(self) -> int:
        return int(self.codes.nbytes + self.ids.nbytes + self.zs.nbytes + self.scodes.nbytes +
                   self.sids.nbytes + self.szs.nbytes + self.grid.P.nbytes)

    def _zproj(self, keys: np.ndarray) -> np.ndarray:
        return self.grid.zproj(keys)

    def project(self, keys: np.ndarray) -> np.ndarray:
        """float64 projections [n, m] of float32 keys (grid parameters fixed on first use)."""
        keys = np.asarray(keys, dtype=np.float32)
        if self.grid.observe(keys) and self.grid.needs_coarser_cell():
            self.rebuild(refit=False)  # a larger key needs a coarser cell
        z = self.grid.zproj(keys)
        if self.grid.origin is None:
            self.grid.fit(z)
        return z

    # ------------------------------------------------------------------ storage
    def add(self, ids: np.ndarray, z: np.ndarray) -> None:
        if not len(ids):
            return
        g = self.grid
        raw = g.raw_cells(z)
        self.clipped += int(((raw < 0) | (raw > GRID_MAX)).any(axis=1).sum())
        codes = g.code(z)
        o = np.argsort(codes, kind="stable")
        codes, ids, z32 = codes[o], np.asarray(ids, np.int64)[o], (z[o] - g.zc0).astype(np.float32)
        pos = np.searchsorted(self.scodes, codes, side="right")
        self.scodes = np.insert(self.scodes, pos, codes)
        self.sids = np.insert(self.sids, pos, ids)
        self.szs = np.insert(self.szs, pos, z32, axis=0)
        if len(self.scodes) > max(4096, len(self.codes) // 16):
            self._merge()
        self.maybe_rebuild()

    def _clear_small(self) -> None:
        self.scodes = np.zeros(0, np.int64)
        self.sids = np.zeros(0, np.int64)
        self.szs = np.zeros((0, self.mf), np.float32)

    def _merge(self) -> None:
        pos = np.searchsorted(self.codes, self.scodes, side="right")
        self.codes = np.insert(self.codes, pos, self.scodes)
        self.ids = np.insert(self.ids, pos, self.sids)
        self.zs = np.insert(self.zs, pos, self.szs, axis=0)
        self._clear_small()

    def remove(self, ids: np.ndarray) -> int:
        """Lazy: the caller guarantees the ids are indexed and no longer alive."""
        self.stale += len(ids)
        return len(ids)

    def maybe_rebuild(self, force: bool = False) -> bool:
        n = self.ntotal
        entries = len(self.codes) + len(self.scodes)
        grow = n >= self.min_train and n >= self.rebuild_growth * max(self.n_at_build, 1)
        # keys that left the fitted extent (drift, outliers): re-fit once they are a quarter of
        # the identities at the last build (amortised O(log n) per identity, whatever the keys do)
        grow = grow or self.clipped >= max(256, self.n_at_build // 4)
        if force or grow or self.stale > max(1024, entries // 4):
            self.rebuild(refit=force or grow)
            return True
        return False

    def reindex(self) -> None:
        """Index every live identity of the source anew (after a snapshot restore)."""
        self.rebuild(refit=True)

    def rebuild(self, refit: bool = True) -> None:
        """Re-index every live identity (refit: new PCA directions and grid extent)."""
        g = self.grid
        ids = np.asarray(self.source.live_ids(), dtype=np.int64)
        n = len(ids)
        if refit and n >= 2:
            rng = np.random.default_rng(self.seed + n)
            samp = ids[np.sort(rng.choice(n, size=min(n, 20000), replace=False))]
            g.fit_directions((keys for _, keys in self.key_blocks(samp, _KEY_BLOCK)), rng)
        z = np.empty((n, self.mf))
        for s, keys in self.key_blocks(ids, _KEY_BLOCK):
            g.observe(keys)
            z[s:s + len(keys)] = g.zproj(keys)
        if refit or g.origin is None:
            g.fit(z)
        else:
            g.coarsen()
        codes = g.code(z) if n else np.zeros(0, np.int64)
        self.clipped = 0
        o = np.argsort(codes, kind="stable")
        self.codes, self.ids, self.zs = codes[o], ids[o], (z[o] - g.zc0).astype(np.float32)
        self._clear_small()
        self.stale = 0
        self.n_at_build = n
        self.rebuilds += 1

    # ------------------------------------------------------------------ candidates
    def candidates_of(self, z: np.ndarray):
        """Yield (query, id) arrays of alive stored identities in neighbour cells (chunked)."""
        n = len(z)
        if n == 0 or self.ntotal == 0:
            return
        g = self.grid
        lo_c, hi_c, valid = g.ranges(g.cells(z))
        levels = [(c, i, zz) for c, i, zz in ((self.codes, self.ids, self.zs),
                                              (self.scodes, self.sids, self.szs)) if len(c)]
        spans = _lookup([c for c, _, _ in levels], lo_c, hi_c, valid)
        cnt = sum((hi - lo).sum(axis=1) for lo, hi in spans)
        self.scanned += int(cnt.sum())
        for s, e in _query_chunks(cnt):
            qs, cs = [], []
            for (codes, ids, zz), (lo, hi) in zip(levels, spans):
                row, pos = _expand(lo[s:e], hi[s:e])
                q = s + row // lo.shape[1]
                near = g.near(z[q], zz[pos])
                qs.append(q[near])
                cs.append(ids[pos[near]])
            q, c = np.concatenate(qs), np.concatenate(cs)
            if self.stale and len(c):
                ok = self.source.alive(c)
                q, c = q[ok], c[ok]
            yield q, c

    def batch_pairs(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (i, j), j < i, of batch items in neighbour cells (a superset of similar pairs)."""
        g = self.grid
        codes = g.code(z)
        order = np.argsort(codes, kind="stable")
        sc = codes[order]
        lo_c, hi_c, valid = g.ranges(g.cells(z))
        (lo, hi), = _lookup([sc], lo_c, hi_c, valid)
        cnt = (hi - lo).sum(axis=1) - 1  # minus the item itself
        self.scanned += int(cnt.sum())
        if int(cnt.sum()) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pis, pjs = [], []
        for s, e in _query_chunks(cnt + 1):
            row, pos = _expand(lo[s:e], hi[s:e])
            i = s + row // lo.shape[1]
            j = order[pos]
            keep = j < i
            i, j = i[keep], j[keep]
            keep = g.near64(z[i], z[j])
            pis.append(i[keep])
            pjs.append(j[keep])
        return np.concatenate(pis), np.concatenate(pjs)
