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

Wide keys (a norm beyond the grid's ``norm_cap`` or a cell index beyond the exact wrap range,
:mod:`~comper_memory.core.grid_cells`) are kept apart, sorted by norm, with their float64
projections: a query's candidates among them are those whose norm lies within ``norm_margin``
of its own and whose projection passes the filter. The projections y the index works on are
[z | norm] (the norm is the last column).

Cell indices wrap around (:mod:`~comper_memory.core.grid_cells`), so a batch whose keys jump
away from the fitted extent spreads over the cells as the stored keys do: its cost stays linear
in its size. Identities added outside the extent (or wide) are counted; once they are a quarter
of the identities at the last build (at least 256) the index re-fits (each re-fit is paid by
n/4 new identities: O(log n) re-fits per identity).
"""
from __future__ import annotations

import numpy as np

from .grid_cells import GridCells
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
        self._clear_wide()
        self.stale = 0
        self.n_at_build = 0
        self.rebuilds = 0

    @property
    def ntotal(self) -> int:
        return int(len(self.codes) + len(self.scodes) + len(self.wids) - self.stale)

    @property
    def nlist(self) -> int:
        """Occupied grid cells (the partition's size; tests and benchmarks report it)."""
        c = np.concatenate([self.codes, self.scodes])
        return int(len(np.unique(c))) if len(c) else 0

    @property
    def n_wide(self) -> int:
        """Entries kept apart from the grid (wide keys, stale ones included)."""
        return int(len(self.wids))

    def bytes_used(self) -> int:
        return int(self.codes.nbytes + self.ids.nbytes + self.zs.nbytes + self.scodes.nbytes +
                   self.sids.nbytes + self.szs.nbytes + self.grid.P.nbytes + self.wnorm.nbytes +
                   self.wids.nbytes + self.wz.nbytes)

    def _zproj(self, keys: np.ndarray) -> np.ndarray:
        """[z | norm] of keys with the current grid (no re-fit)."""
        keys = np.asarray(keys, dtype=np.float32)
        return np.column_stack([self.grid.zproj(keys), self.grid.norms(keys)])

    def _outside(self, y: np.ndarray) -> np.ndarray:
        """bool [n]: points outside the fitted extent, or wide."""
        z, nrm = y[:, :-1], y[:, -1]
        return self.grid.outside(z) | ~self.grid.grid_store(z, nrm)

    def project(self, keys: np.ndarray) -> np.ndarray:
        """float64 [z | norm] [n, mf + 1] of float32 keys (grid parameters fixed on first use)."""
        keys = np.asarray(keys, dtype=np.float32)
        g = self.grid
        y = self._zproj(keys)
        if g.origin is None:
            g.fit(y[:, :-1], y[:, -1])
            return y
        z, nrm = y[:, :-1], y[:, -1]
        if g.observe(nrm[g.grid_query(z, nrm)]) and g.needs_coarser_cell():
            self.rebuild(refit=False)  # a larger key needs a coarser cell (z does not change)
        return y

    # ------------------------------------------------------------------ storage
    def add(self, ids: np.ndarray, y: np.ndarray) -> None:
        if not len(ids):
            return
        g = self.grid
        ids = np.asarray(ids, np.int64)
        self.clipped += int(self._outside(y).sum())
        z, nrm = y[:, :-1], y[:, -1]
        on = g.grid_store(z, nrm)
        if not on.all():
            self._add_wide(ids[~on], z[~on], nrm[~on])
            ids, z = ids[on], z[on]
        if len(ids):
            codes = g.code(z)
            o = np.argsort(codes, kind="stable")
            codes, ids, z32 = codes[o], ids[o], (z[o] - g.zc0).astype(np.float32)
            pos = np.searchsorted(self.scodes, codes, side="right")
            self.scodes = np.insert(self.scodes, pos, codes)
            self.sids = np.insert(self.sids, pos, ids)
            self.szs = np.insert(self.szs, pos, z32, axis=0)
            if len(self.scodes) > max(4096, len(self.codes) // 16):
                self._merge()
        self.maybe_rebuild()

    def _clear_wide(self) -> None:
        self.wnorm = np.zeros(0)
        self.wids = np.zeros(0, np.int64)
        self.wz = np.zeros((0, self.mf))

    def _add_wide(self, ids: np.ndarray, z: np.ndarray, nrm: np.ndarray) -> None:
        o = np.argsort(nrm, kind="stable")
        pos = np.searchsorted(self.wnorm, nrm[o], side="right")
        self.wnorm = np.insert(self.wnorm, pos, nrm[o])
        self.wids = np.insert(self.wids, pos, ids[o])
        self.wz = np.insert(self.wz, pos, z[o], axis=0)

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
        entries = len(self.codes) + len(self.scodes) + len(self.wids)
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
        """Re-index every live identity (refit: new PCA directions, grid extent and norm cap)."""
        g = self.grid
        ids = np.asarray(self.source.live_ids(), dtype=np.int64)
        n = len(ids)
        if refit and n >= 2:
            rng = np.random.default_rng(self.seed + n)
            samp = ids[np.sort(rng.choice(n, size=min(n, 20000), replace=False))]
            g.fit_directions((keys for _, keys in self.key_blocks(samp, _KEY_BLOCK)), rng)
        z = np.empty((n, self.mf))
        nrm = np.empty(n)
        for s, keys in self.key_blocks(ids, _KEY_BLOCK):
            z[s:s + len(keys)] = g.zproj(keys)
            nrm[s:s + len(keys)] = g.norms(keys)
        if refit or g.origin is None:
            g.fit(z, nrm)
        else:
            g.observe(nrm[g.grid_query(z, nrm)])
            g.coarsen()
        on = g.grid_store(z, nrm)
        self._clear_wide()
        if not on.all():
            self._add_wide(ids[~on], z[~on], nrm[~on])
            ids, z = ids[on], z[on]
        codes = g.code(z) if len(z) else np.zeros(0, np.int64)
        self.clipped = 0
        o = np.argsort(codes, kind="stable")
        self.codes, self.ids, self.zs = codes[o], ids[o], (z[o] - g.zc0).astype(np.float32)
        self._clear_small()
        self.stale = 0
        self.n_at_build = n
        self.rebuilds += 1

    # ------------------------------------------------------------------ candidates
    def candidates_of(self, y: np.ndarray):
        """Yield (query, id) arrays of alive stored identities in neighbour cells and of wide
        keys within the norm margin (chunked; the wide chunk may repeat a query of a grid one)."""
        n = len(y)
        if n == 0 or self.ntotal == 0:
            return
        if len(self.wids):
            yield from self._wide_candidates(y)
        z, nrm = y[:, :-1], y[:, -1]
        sub = np.flatnonzero(self.grid.grid_query(z, nrm))
        if len(self.codes) + len(self.scodes) == 0 or not len(sub):
            return
        if len(sub) == n:
            yield from self._grid_candidates(z)
        else:
            for q, c in self._grid_candidates(z[sub]):
                yield sub[q], c

    def _wide_candidates(self, y: np.ndarray):
        g = self.grid
        z, nrm = y[:, :-1], y[:, -1]
        m = g.norm_margin(2.0 * (nrm + g.r) + 1.0)
        lo = np.searchsorted(self.wnorm, nrm - m, side="left")
        hi = np.searchsorted(self.wnorm, nrm + m, side="right")
        cnt = hi - lo
        self.scanned += int(cnt.sum())
        for s, e in _query_chunks(cnt):
            row, pos = _expand(lo[s:e], hi[s:e])
            q = s + row
            keep = g.near64(z[q], self.wz[pos], np.maximum(nrm[q], self.wnorm[pos]))
            q, c = q[keep], self.wids[pos[keep]]
            if self.stale and len(c):
                ok = self.source.alive(c)
                q, c = q[ok], c[ok]
            yield q, c

    def _grid_candidates(self, z: np.ndarray):
        n = len(z)
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

    def batch_pairs(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (i, j), j < i, of batch items in neighbour cells, or within the norm margin of
        each other when either may be a wide key (a superset of similar pairs)."""
        g = self.grid
        z, nrm = y[:, :-1], y[:, -1]
        on = g.grid_query(z, nrm)
        wide = g.wide_query(z, nrm)
        if on.all() and not wide.any():
            return self._grid_pairs(z)
        parts = []
        sub = np.flatnonzero(on)
        if len(sub) > 1:
            i, j = self._grid_pairs(z[sub])
            parts.append((sub[i], sub[j]))
        sub = np.flatnonzero(wide)
        if len(sub) > 1:
            parts.append(self._norm_pairs(z[sub], nrm[sub], sub))
        if not parts:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        if len(parts) == 1:
            return parts[0]
        n = len(y)
        code = np.unique(np.concatenate([i * n + j for i, j in parts]))  # an item in both: once
        return code // n, code % n

    def _norm_pairs(self, z: np.ndarray, nrm: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (idx[i], idx[j]), idx[j] < idx[i], whose norms differ by at most the margin and
        whose projections pass the filter (idx increasing)."""
        g = self.grid
        o = np.argsort(nrm, kind="stable")
        sn = nrm[o]
        m = g.norm_margin(2.0 * (sn + g.r) + 1.0)
        lo = np.searchsorted(sn, sn - m, side="left")
        hi = np.searchsorted(sn, sn + m, side="right")
        cnt = hi - lo
        self.scanned += int(cnt.sum()) - len(sn)
        pis, pjs = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        for s, e in _query_chunks(cnt):
            row, pos = _expand(lo[s:e], hi[s:e])
            i, j = o[s + row], o[pos]
            keep = j < i
            i, j = i[keep], j[keep]
            keep = g.near64(z[i], z[j], np.maximum(nrm[i], nrm[j]))
            pis.append(idx[i[keep]])
            pjs.append(idx[j[keep]])
        return np.concatenate(pis), np.concatenate(pjs)

    def _grid_pairs(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
