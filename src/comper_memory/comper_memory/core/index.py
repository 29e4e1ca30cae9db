"""Exact similarity index: faiss IVF over an orthonormal projection, exact float64 re-check.

Decision rule (method.md section 1): a store of n transitions is processed as if sequentially;
transition i joins the nearest live identity whose key is within ``delta`` (squared L2, computed
exactly in float64 by :func:`~comper_memory.core.keys.exact_sq_dist`; ties -> lowest identity id),
which may be an identity created by an earlier transition of the same batch; otherwise it
creates a new identity. Identity ids are allocated in increasing order, so "lowest id" is also
"oldest", and an existing identity wins a tie against one created in the same batch.

Why it is exact (no similar pair can be missed), with r = sqrt(delta):

* P is a matrix with orthonormal rows (m x D), so |P(x - y)| <= |x - y|: a stored key within r
  of the query has its projection within r of the query's projection. Projections are stored
  as float32 (y = fl32(P x - c)); the casting error is bounded and added to the radius: r'.
* The projected points are partitioned by k-means centroids; every stored point is assigned to
  its nearest centroid (computed in float64 in m dimensions, error bound eta). If y_x is within
  r' of y_q, then d(y_q, c_list(x)) <= d(y_q, c_nearest(q)) + 2 r' + 4 eta (triangle inequality),
  so probing exactly the lists that satisfy this bound finds it (a variable number per query,
  usually one; passed to faiss as pre-assigned lists padded with -1).
* Inside the probed lists faiss computes direct (not expanded) fp32 distances in m dims, whose
  relative error is below 1e-6; the range radius carries that margin.
* Every candidate that survives is re-checked against its full key in float64.

The partition affects speed only, never a decision, so it is rebuilt (re-trained) freely as the
number of identities grows. Cost per store: one float64 matmul against the centroids, one faiss
range search over the probed lists, and float64 re-checks of the few survivors: it does not grow
linearly with the number of identities.
"""
from __future__ import annotations

from typing import Callable

import faiss
import numpy as np

from .keys import exact_sq_dist

__all__ = ["ExactIndex", "GridIndex", "ResolveResult", "make_index"]

_U32 = float(np.finfo(np.float32).eps)  # 1.19e-7 (2 x unit roundoff, conservative)
_SUBSPACE = 64  # keys longer than this are projected through a random orthonormal 64-d subspace first
_EXACT_CHUNK_VALUES = 1 << 22  # float64 values per exact re-check chunk (32 MiB)


class ResolveResult:
    """Per transition of a batch: ``existing`` id it joins (or -1), else ``batch`` index j of the
    earlier transition of the same batch whose new identity it joins (or -1); both -1: creates."""

    __slots__ = ("existing", "batch", "candidates_checked")

    def __init__(self, existing: np.ndarray, batch: np.ndarray, candidates_checked: int):
        self.existing = existing
        self.batch = batch
        self.candidates_checked = candidates_checked

    @property
    def creates(self) -> np.ndarray:
        return (self.existing < 0) & (self.batch < 0)


class ExactIndex:
    """Exact radius-delta nearest-identity index (see module docstring)."""

    engine = "ivf"

    def __init__(self, key_dim: int, delta: float, *, projection_dim: int = 8,
                 min_train: int = 2048, list_size: int = 256, max_lists: int = 4096,
                 rebuild_growth: float = 4.0, seed: int = 0):
        self.key_dim = int(key_dim)
        self.delta = float(delta)
        self.r = float(np.sqrt(self.delta))
        self.min_train = int(min_train)
        self.list_size = int(list_size)
        self.max_lists = int(max_lists)
        self.rebuild_growth = float(rebuild_growth)
        self.seed = int(seed)
        rng = np.random.default_rng(seed)
        if self.key_dim <= projection_dim:
            self.m = self.key_dim
            self.P = None  # identity: keys are already float32, the "projection" is exact
        else:
            self.m = int(projection_dim)
            q, _ = np.linalg.qr(rng.standard_normal((self.key_dim, self.m)))
            self.P = np.ascontiguousarray(q.T)  # [m, D], orthonormal rows
        self.center: np.ndarray | None = None   # float64 [m], fixed at the first add
        self.max_key_norm = 0.0   # max |x| over keys seen (bounds projection error)
        self.max_y_norm = 0.0     # max |y| over projected points seen (bounds casting error)
        self.centroids = np.zeros((1, self.m))  # float64 [nlist, m]
        self._cnorm = np.zeros(1)
        self.ntotal_at_build = 0
        self._make_faiss(1)

    # ------------------------------------------------------------------ internals
    def _make_faiss(self, nlist: int) -> None:
        quantizer = faiss.IndexFlatL2(self.m)
        quantizer.add(self.centroids.astype(np.float32))
        self.ivf = faiss.IndexIVFFlat(quantizer, self.m, nlist)
        self.ivf.is_trained = True
        self._quantizer = quantizer  # keep alive

    @property
    def ntotal(self) -> int:
        return int(self.ivf.ntotal)

    @property
    def nlist(self) -> int:
        return int(self.centroids.shape[0])

    def bytes_used(self) -> int:
        # faiss IVF-Flat: m float32 + one int64 id per vector, plus centroids
        return self.ntotal * (4 * self.m + 8) + self.centroids.nbytes * 2

    def project(self, keys: np.ndarray) -> np.ndarray:
        """float32 projected points y = fl32(P x - c) [n, m]."""
        keys = np.asarray(keys, dtype=np.float32)
        if self.P is None:
            z = keys.astype(np.float64)
        else:
            z = keys.astype(np.float64) @ self.P.T
        if self.center is None:
            self.center = z.mean(axis=0) if len(z) else np.zeros(self.m)
        y = (z - self.center).astype(np.float32)
        if len(keys):
            self.max_key_norm = max(self.max_key_norm, float(np.sqrt(
                np.einsum("ij,ij->i", keys, keys, dtype=np.float64).max())))
            self.max_y_norm = max(self.max_y_norm, float(np.sqrt(
                np.einsum("ij,ij->i", y, y, dtype=np.float64).max())))
        return y

    def _radius_proj(self) -> float:
        """r' : radius in projected float32 space that contains every key within r."""
        proj_err = 0.0 if self.P is None else 1e-12 * (1.0 + self.max_key_norm) * np.sqrt(self.key_dim)
        cast_err = _U32 * (self.max_y_norm + 1.0)
        return self.r * (1.0 + 1e-9) + 2.0 * (proj_err + cast_err)

    def _eta(self) -> float:
        cmax = float(self._cnorm.max()) if len(self._cnorm) else 0.0
        return float(np.sqrt(64 * np.finfo(np.float64).eps * (self.max_y_norm ** 2 + cmax + 1.0) * (self.m + 2)))

    def _centroid_d2(self, y: np.ndarray) -> np.ndarray:
        y64 = y.astype(np.float64)
        d2 = (y64 * y64).sum(axis=1)[:, None] + self._cnorm[None, :] - 2.0 * (y64 @ self.centroids.T)
        np.maximum(d2, 0.0, out=d2)
        return d2

    def _nearest_k(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """faiss proposes the K nearest centroids; float64 distances of those; fp32 error bound."""
        K = min(self.nlist, 8)
        _, cand = self._quantizer.search(np.ascontiguousarray(y, dtype=np.float32), K)
        y64 = y.astype(np.float64)
        d2 = ((y64[:, None, :] - self.centroids[cand]) ** 2).sum(axis=2)
        ysq = (y64 * y64).sum(axis=1)
        # fp32 expanded distances err by at most ~ (m + 2) u32 (|y|^2 + |c|^2) (squared units)
        err = 4.0 * (self.m + 2) * _U32 * (ysq + float(self._cnorm.max()) + 1.0)
        return cand, d2, err

    def _assign(self, y: np.ndarray) -> np.ndarray:
        """Nearest centroid of each point (float64; a list outside faiss's K proposals can only
        be nearer if the K-th proposal is within the fp32 error, then all centroids are checked)."""
        if self.nlist == 1:
            return np.zeros(len(y), dtype=np.int64)
        out = np.empty(len(y), dtype=np.int64)
        step = 1 << 16
        for s in range(0, len(y), step):
            ys = y[s:s + step]
            cand, d2, err = self._nearest_k(ys)
            best = d2.argmin(axis=1)
            a = cand[np.arange(len(ys)), best]
            dmin = d2[np.arange(len(ys)), best]
            bad = np.flatnonzero((cand.shape[1] < self.nlist) & (d2.max(axis=1) - 2.0 * err <= dmin))
            if len(bad):
                a[bad] = self._centroid_d2(ys[bad]).argmin(axis=1)
            out[s:s + step] = a
        return out

    def _probe_lists(self, y: np.ndarray) -> np.ndarray:
        """[n, w] list numbers to probe per query (padded with -1).

        faiss (fp32) proposes the K nearest centroids; their distances are recomputed in float64.
        A row is settled when its K-th float64 distance exceeds the probe bound by more than the
        fp32 ranking error (so no list outside the K can be within the bound); other rows fall
        back to float64 distances to every centroid."""
        n = len(y)
        if self.nlist == 1:
            return np.zeros((n, 1), dtype=np.int64)
        slack = 2.0 * self._radius_proj() + 4.0 * self._eta()
        cand, d2, err = self._nearest_k(y)
        K = cand.shape[1]
        d = np.sqrt(d2)
        dmin = d.min(axis=1)
        kth = d.max(axis=1)
        settled = (K == self.nlist) | (kth * kth > (dmin + slack) ** 2 + 2.0 * err)
        lists = np.where(d <= (dmin + slack)[:, None], cand, -1)
        bad = np.flatnonzero(~settled)
        if len(bad):
            dfull = np.sqrt(self._centroid_d2(y[bad]))
            mask = dfull <= dfull.min(axis=1, keepdims=True) + slack
            width = max(K, int(mask.sum(axis=1).max()))
            ext = np.full((n, width), -1, dtype=np.int64)
            ext[:, :K] = lists
            ext[bad] = -1
            for r, row in zip(bad, mask):
                js = np.flatnonzero(row)
                ext[r, :len(js)] = js
            lists = ext
        # compact: drop all-(-1) columns
        keep = (lists >= 0).any(axis=0)
        lists = lists[:, keep] if keep.any() else lists[:, :1]
        return np.ascontiguousarray(lists, dtype=np.int64)

    def _add_faiss(self, ids: np.ndarray, y: np.ndarray) -> None:
        if not len(ids):
            return
        a = self._assign(y)
        y = np.ascontiguousarray(y, dtype=np.float32)
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        self.ivf.add_core(len(ids), faiss.swig_ptr(y), faiss.swig_ptr(ids), faiss.swig_ptr(a))

    def _all_vectors(self) -> tuple[np.ndarray, np.ndarray]:
        invl = self.ivf.invlists
        ids_parts, y_parts = [], []
        for lst in range(invl.nlist):
            sz = invl.list_size(lst)
            if sz == 0:
                continue
            ids_parts.append(faiss.rev_swig_ptr(invl.get_ids(lst), sz).copy())
            codes = faiss.rev_swig_ptr(invl.get_codes(lst), sz * self.m * 4).copy()
            y_parts.append(codes.view(np.float32).reshape(sz, self.m))
        if not ids_parts:
            return np.zeros(0, np.int64), np.zeros((0, self.m), np.float32)
        return np.concatenate(ids_parts), np.concatenate(y_parts)

    def maybe_rebuild(self, force: bool = False) -> bool:
        n = self.ntotal
        if not force and (n < self.min_train or n < self.rebuild_growth * max(self.ntotal_at_build, 1)):
            return False
        ids, y = self._all_vectors()
        nlist = int(min(self.max_lists, max(1, n // self.list_size)))
        if nlist > 1:
            km = faiss.Kmeans(self.m, nlist, niter=10, seed=self.seed + n, verbose=False,
                              max_points_per_centroid=64)
            km.train(y)
            self.centroids = km.centroids.astype(np.float64)
        else:
            self.centroids = np.zeros((1, self.m))
        self._cnorm = (self.centroids ** 2).sum(axis=1)
        self._make_faiss(nlist)
        self._add_faiss(ids, y)
        self.ntotal_at_build = n
        return True

    # ------------------------------------------------------------------ public API
    def add(self, ids: np.ndarray, y: np.ndarray) -> None:
        """Add identities (ids int64) with their projected points y (from :meth:`project`)."""
        self._add_faiss(ids, y)
        self.maybe_rebuild()

    def remove(self, ids: np.ndarray) -> int:
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        if not len(ids):
            return 0
        return int(self.ivf.remove_ids(faiss.IDSelectorBatch(len(ids), faiss.swig_ptr(ids))))

    def candidates(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lims [n+1], ids) of stored identities whose projection lies within r' of each query.

        A superset of the identities within delta of each query (never misses one)."""
        n = len(y)
        if self.ntotal == 0 or n == 0:
            return np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int64)
        lists = self._probe_lists(y)
        rp = self._radius_proj()
        radius = float(rp * rp * (1.0 + 1e-5) + 1e-30)
        self.ivf.nprobe = lists.shape[1]
        res = faiss.RangeSearchResult(n)
        yq = np.ascontiguousarray(y, dtype=np.float32)
        coarse = np.zeros(lists.shape, dtype=np.float32)
        sp = faiss.swig_ptr
        self.ivf.range_search_preassigned_c(n, sp(yq), radius, sp(lists), sp(coarse), res)
        lims = faiss.rev_swig_ptr(res.lims, n + 1).copy().astype(np.int64)
        ids = faiss.rev_swig_ptr(res.labels, int(lims[-1])).copy().astype(np.int64)
        return lims, ids

    def _batch_pairs(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (i, j), j < i, of batch items whose projections lie within r' (float64).

        Sweep on the first projected coordinate (|y_i0 - y_j0| <= |y_i - y_j|), then a full
        m-d float64 check of the pairs inside the window."""
        n = len(y)
        rp = self._radius_proj()
        thr = rp * rp * (1.0 + 1e-6) + 64 * np.finfo(np.float64).eps * (self.max_y_norm ** 2 + 1.0)
        w = np.sqrt(thr) * (1.0 + 1e-9)
        y64 = y.astype(np.float64)
        order = np.argsort(y64[:, 0], kind="stable")
        c0 = y64[order, 0]
        hi = np.searchsorted(c0, c0 + w, side="right")
        cnt = hi - np.arange(n) - 1  # partners after each sorted position
        tot = int(cnt.sum())
        if tot == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        a = np.repeat(np.arange(n), cnt)
        b = a + 1 + (np.arange(tot) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        ia, ib = order[a], order[b]
        d2 = ((y64[ia] - y64[ib]) ** 2).sum(axis=1)
        ok = d2 <= thr
        ia, ib = ia[ok], ib[ok]
        return np.maximum(ia, ib), np.minimum(ia, ib)

    def resolve(self, keys: np.ndarray, y: np.ndarray,
                key_fn: Callable[[np.ndarray], np.ndarray]) -> ResolveResult:
        """Decide, exactly and as if sequentially, what each transition of a batch joins.

        keys: float32 [n, D] batch keys; y: their projections; key_fn(ids) -> float32 keys of
        stored identities (reconstructed from their representatives)."""
        n = len(keys)
        delta = self.delta
        existing = np.full(n, -1, dtype=np.int64)
        best_d = np.full(n, np.inf)
        checked = 0
        lims, cand = self.candidates(y)
        if len(cand):
            qidx = np.repeat(np.arange(n), np.diff(lims))
            uniq, inv = np.unique(cand, return_inverse=True)
            ukeys = key_fn(uniq)
            dist = np.empty(len(cand))
            step = max(1, _EXACT_CHUNK_VALUES // max(1, self.key_dim))
            for s in range(0, len(cand), step):
                dist[s:s + step] = exact_sq_dist(keys[qidx[s:s + step]], ukeys[inv[s:s + step]])
            checked += len(cand)
            ok = dist <= delta
            if ok.any():
                q, c, d = qidx[ok], cand[ok], dist[ok]
                order = np.lexsort((c, d, q))  # by query, then distance, then id
                q, c, d = q[order], c[order], d[order]
                first = np.ones(len(q), dtype=bool)
                first[1:] = q[1:] != q[:-1]
                existing[q[first]] = c[first]
                best_d[q[first]] = d[first]
        batch = np.full(n, -1, dtype=np.int64)
        if n > 1:
            pi, pj = self._batch_pairs(y)
            if len(pi):
                order = np.lexsort((pj, pi))
                pi, pj = pi[order], pj[order]
                starts = np.searchsorted(pi, np.arange(n))
                ends = np.searchsorted(pi, np.arange(n), side="right")
                creates = existing < 0
                for i in np.unique(pi):
                    js = pj[starts[i]:ends[i]]
                    js = js[creates[js]]
                    if not len(js):
                        continue
                    d = exact_sq_dist(keys[i][None, :], keys[js])
                    checked += len(js)
                    ok = d <= delta
                    if not ok.any():
                        continue
                    js, d = js[ok], d[ok]
                    k = int(np.lexsort((js, d))[0])  # nearest, then earliest (lowest new id)
                    if d[k] < best_d[i]:  # strictly nearer than the best existing (which wins ties)
                        existing[i] = -1
                        best_d[i] = d[k]
                        batch[i] = js[k]
                        creates[i] = False
        return ResolveResult(existing, batch, checked)


# ====================================================================== grid engine
_GRID_BITS = 21
# Largest cell index: one below 2^21 - 1, so the largest code (all axes at _GRID_MAX) plus one, the
# exclusive end of a code range in _lookup, still fits in int64 (at 2^21 - 1 it wrapped to a
# negative number and queries in the top corner of the grid found nothing: session 4).
_GRID_MAX = (1 << _GRID_BITS) - 2
_EPS64 = float(np.finfo(np.float64).eps)
_PAIR_CHUNK = 1 << 21  # candidate pairs expanded at once (bounds temporary memory)
_NORM_HEADROOM = 4.0   # cells are sized for keys up to this many times the largest norm seen
_GRID_HEADROOM = 16.0  # the grid spans this many times the fitted (2nd-98th percentile) extent


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


class GridIndex:
    """Exact radius-delta index over a sorted-cell-code grid (low-dimensional keys).

    Why it is exact (no identity within delta can be missed), with r = sqrt(delta):

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
      projection lies within the conservative mf-d radius of ``_radius_proj`` (|P(x - y)| <=
      |x - y| (1 + e_o) holds for all mf coordinates together). With 3 coordinates, keys that
      vary along many directions (Atari frames) pile up in few cells; 8 coordinates cut the exact
      re-checks on real Freeway transitions from ~24 per stored transition at 5,000 identities to
      ~1 (the re-stores' own identities): benchmarks/memory_atari_bench.py.
    * Every candidate that is still alive is re-checked against its full key in float64
      (``exact_sq_dist``); the grid only decides which identities are looked at.

    Storage: two sorted levels (code int64, id int64, projection mf float32): a large main level
    and a small level that new identities are inserted into (``np.insert``, O(small)); the small
    level is merged into the main one when it exceeds main/16 (amortised O(1) per identity).
    Removal is lazy: evicted
    ids stay as stale entries (ids are never reused, and candidates are filtered with
    ``alive``) until a rebuild, which happens when stale entries exceed a quarter of the
    entries, when identities grew ``rebuild_growth``-fold since the last build (re-fitting the
    PCA directions and the grid extent), or when a key's norm would need a coarser cell.
    """

    engine = "grid"

    def __init__(self, key_dim: int, delta: float, *, keys_of: Callable[[np.ndarray], np.ndarray],
                 alive: Callable[[np.ndarray], np.ndarray], live_ids: Callable[[], np.ndarray],
                 grid_dims: int = 3, filter_dims: int = 8, min_train: int = 2048,
                 rebuild_growth: float = 4.0, seed: int = 0):
        self.key_dim = int(key_dim)
        self.delta = float(delta)
        self.r = float(np.sqrt(self.delta))
        self.m = int(min(grid_dims, self.key_dim, 3))          # cell axes
        self.mf = int(max(self.m, min(filter_dims, self.key_dim, _SUBSPACE)))  # filter axes (first m = cells)
        self.min_train = int(min_train)
        self.rebuild_growth = float(rebuild_growth)
        self.seed = int(seed)
        self._keys_of, self._alive, self._live_ids = keys_of, alive, live_ids
        rng = np.random.default_rng(seed)
        q, _ = np.linalg.qr(rng.standard_normal((self.key_dim, self.mf)))
        self._set_projection(np.ascontiguousarray(q.T))
        self.max_key_norm = 0.0
        self.origin: np.ndarray | None = None
        self.cell = np.zeros(self.m)            # side of the cells, per axis
        self.zc0 = np.zeros(self.mf)            # stored projections are fl32(z - zc0)
        self.clipped = 0                        # identities added outside the grid since the last build
        self.scanned = 0                        # candidate pairs taken from neighbour cells (cost counter)
        self.codes = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self.zs = np.zeros((0, self.mf), np.float32)
        self.scodes = np.zeros(0, np.int64)
        self.sids = np.zeros(0, np.int64)
        self.szs = np.zeros((0, self.mf), np.float32)
        self.stale = 0
        self.n_at_build = 0
        self.rebuilds = 0
        sh = [_GRID_BITS * (self.m - 1 - d) for d in range(self.m)]
        self._shift = np.asarray(sh, dtype=np.int64)
        offs = np.array(np.meshgrid(*[[-1, 0, 1]] * (self.m - 1), indexing="ij")).reshape(self.m - 1, -1).T \
            if self.m > 1 else np.zeros((1, 0), np.int64)
        self._offs = offs.astype(np.int64)  # [3^(m-1), m-1]

    # ------------------------------------------------------------------ geometry
    def _set_projection(self, P: np.ndarray) -> None:
        self.P = np.ascontiguousarray(P, dtype=np.float64)
        g = self.P @ self.P.T - np.eye(len(self.P))
        self.e_o = float(np.sqrt((g * g).sum())) + 1e-15

    def _err(self, norm: float | None = None) -> float:
        norm = self.max_key_norm if norm is None else norm
        return 2.0 * (self.key_dim + 2) * _EPS64 * (norm + 1.0) * 4.0

    def _min_cell(self, headroom: float = 1.0) -> float:
        """Smallest exact cell side for keys up to ``headroom`` x the largest norm seen. Cells are
        made for 4x the norm (``_NORM_HEADROOM``), so keys whose norm keeps growing (drift) force
        a coarser cell (a rebuild) only each time their norm quadruples, not at every store."""
        return (self.r * (1.0 + self.e_o) + self._err(self.max_key_norm * headroom)) * (1.0 + 1e-7) + 1e-300

    def _radius_proj(self) -> float:
        """Radius in the mf-d filter space containing every point within r of a query, both in
        float64: |P(x - y)| <= |x - y| (1 + e_o), plus the float64 rounding of z (``_err`` per
        coordinate, sqrt(mf) of it in norm, for query and point)."""
        err = self._err() * float(np.sqrt(self.mf))
        return (self.r * (1.0 + self.e_o) + err) * (1.0 + 1e-7)

    def _near(self, zq: np.ndarray, zs: np.ndarray) -> np.ndarray:
        """Conservative filter of stored points (never drops a point within r): zq float64
        projections of the queries, zs the stored fl32(z - zc0). The float32 rounding of a stored
        point is at most 2^-24 |z - zc0| per coordinate, so each candidate's radius carries its own
        rounding (a point far from the others, e.g. a huge key value, widens only its own radius)."""
        zs64 = zs.astype(np.float64)
        d = (zq - self.zc0) - zs64
        d2 = np.einsum("ij,ij->i", d, d)
        cast = 2.0 * _U32 * (np.sqrt(np.einsum("ij,ij->i", zs64, zs64)) + 1.0)
        rp = self._radius_proj() + cast * (1.0 + 1e-7)
        return d2 <= rp * rp * (1.0 + 1e-9) + 1e-300

    def _near64(self, zi: np.ndarray, zj: np.ndarray) -> np.ndarray:
        """The same filter between two float64 projections (pairs inside one batch)."""
        d = zi - zj
        d2 = np.einsum("ij,ij->i", d, d)
        rp = self._radius_proj()
        return d2 <= rp * rp * (1.0 + 1e-9) + 1e-300

    def _zproj(self, keys: np.ndarray) -> np.ndarray:
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

    def _fit_grid(self, z: np.ndarray) -> None:
        """Per-axis cells over a robust extent: the 2nd-98th percentile range of the points,
        widened _GRID_HEADROOM-fold around its centre (so keys may drift far before they leave
        the grid, and one outlying value cannot stretch the cells); never finer than the
        exactness bound ``_min_cell``. Points outside are clipped into the edge cells (still
        exact) and counted in ``clipped``, which triggers a re-fit (``maybe_rebuild``)."""
        c = self._min_cell(_NORM_HEADROOM)
        if len(z):
            sub = z if len(z) <= 20000 else z[np.random.default_rng(self.seed).choice(
                len(z), 20000, replace=False)]
            zc = sub[:, :self.m]
            lo, hi = np.quantile(zc, [0.02, 0.98], axis=0) if len(zc) >= 16 else (
                zc.min(axis=0), zc.max(axis=0))
            span = np.maximum(hi - lo, 0.0)
            cell = np.maximum(c, span * _GRID_HEADROOM / (_GRID_MAX - 4))
            self.origin = (lo + hi) / 2.0 - cell * (_GRID_MAX / 2.0)
            self.zc0 = np.median(sub, axis=0)
        else:
            cell = np.full(self.m, c)
            self.origin = -cell * (_GRID_MAX / 2.0)
            self.zc0 = np.zeros(self.mf)
        self.cell = cell

    def _code(self, z: np.ndarray) -> np.ndarray:
        return (self._cells(z) << self._shift).sum(axis=1)

    def _raw_cells(self, z: np.ndarray) -> np.ndarray:
        return np.floor((z[:, :self.m] - self.origin) / self.cell)

    def _cells(self, z: np.ndarray) -> np.ndarray:
        t = self._raw_cells(z)
        np.clip(t, 0, _GRID_MAX, out=t)
        return t.astype(np.int64)

    # ------------------------------------------------------------------ public
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
                   self.sids.nbytes + self.szs.nbytes + self.P.nbytes)

    def project(self, keys: np.ndarray) -> np.ndarray:
        """float64 projections [n, m] of float32 keys (grid parameters fixed on first use)."""
        keys = np.asarray(keys, dtype=np.float32)
        if len(keys):
            nrm = float(np.sqrt(np.einsum("ij,ij->i", keys, keys, dtype=np.float64).max()))
            if nrm > self.max_key_norm:
                self.max_key_norm = nrm
                if self.origin is not None and self._min_cell() > float(self.cell.min()):
                    self.rebuild(refit=False)  # a larger key needs a coarser cell
        z = self._zproj(keys)
        if self.origin is None:
            self._fit_grid(z)
        return z

    def add(self, ids: np.ndarray, z: np.ndarray) -> None:
        if not len(ids):
            return
        raw = self._raw_cells(z)
        self.clipped += int(((raw < 0) | (raw > _GRID_MAX)).any(axis=1).sum())
        codes = self._code(z)
        o = np.argsort(codes, kind="stable")
        codes, ids, z32 = codes[o], np.asarray(ids, np.int64)[o], (z[o] - self.zc0).astype(np.float32)
        pos = np.searchsorted(self.scodes, codes, side="right")
        self.scodes = np.insert(self.scodes, pos, codes)
        self.sids = np.insert(self.sids, pos, ids)
        self.szs = np.insert(self.szs, pos, z32, axis=0)
        if len(self.scodes) > max(4096, len(self.codes) // 16):
            self._merge()
        self.maybe_rebuild()

    def _merge(self) -> None:
        pos = np.searchsorted(self.codes, self.scodes, side="right")
        self.codes = np.insert(self.codes, pos, self.scodes)
        self.ids = np.insert(self.ids, pos, self.sids)
        self.zs = np.insert(self.zs, pos, self.szs, axis=0)
        self.scodes = np.zeros(0, np.int64)
        self.sids = np.zeros(0, np.int64)
        self.szs = np.zeros((0, self.mf), np.float32)

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

    def rebuild(self, refit: bool = True) -> None:
        """Re-index every live identity (refit: new PCA directions and grid extent)."""
        ids = np.asarray(self._live_ids(), dtype=np.int64)
        n = len(ids)
        step = max(1, (1 << 22) // max(1, self.key_dim))
        if refit and n >= 2:
            rng = np.random.default_rng(self.seed + n)
            samp = np.sort(rng.choice(n, size=min(n, 20000), replace=False))
            X = self._keys_of(ids[samp]).astype(np.float64)
            if self.key_dim > _SUBSPACE:
                q, _ = np.linalg.qr(rng.standard_normal((self.key_dim, _SUBSPACE)))
                R = np.ascontiguousarray(q.T)  # [64, D] orthonormal rows
                X = X @ R.T
            else:
                R = None
            # robust directions: each column winsorised at its 1st / 99th percentile, so a few
            # outlying keys (one huge value) cannot take over an axis (speed only, never results)
            if len(X) >= 100:
                lo, hi = np.quantile(X, [0.01, 0.99], axis=0)
                np.clip(X, lo, hi, out=X)
            X -= X.mean(axis=0)
            w, V = np.linalg.eigh(X.T @ X)
            top = V[:, np.argsort(w)[::-1][:self.mf]].T  # [mf, d] orthonormal rows, largest first
            P = top if R is None else top @ R
            self._set_projection(P)
        z = np.empty((n, self.mf))
        for s in range(0, n, step):
            keys = self._keys_of(ids[s:s + step])
            if len(keys):
                self.max_key_norm = max(self.max_key_norm, float(np.sqrt(
                    np.einsum("ij,ij->i", keys, keys, dtype=np.float64).max())))
            z[s:s + step] = self._zproj(keys)
        if refit or self.origin is None:
            self._fit_grid(z)
        else:
            self.cell = np.maximum(self.cell, self._min_cell(_NORM_HEADROOM))
        codes = self._code(z) if n else np.zeros(0, np.int64)
        self.clipped = 0
        o = np.argsort(codes, kind="stable")
        self.codes, self.ids, self.zs = codes[o], ids[o], (z[o] - self.zc0).astype(np.float32)
        self.scodes = np.zeros(0, np.int64)
        self.sids = np.zeros(0, np.int64)
        self.szs = np.zeros((0, self.mf), np.float32)
        self.stale = 0
        self.n_at_build = n
        self.rebuilds += 1

    # ------------------------------------------------------------------ search
    def _ranges(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per query and neighbour column: (lo_code, hi_code, valid) [n, 3^(m-1)]."""
        m = self.m
        last = cells[:, m - 1]
        lo_last = np.maximum(last - 1, 0)[:, None]
        hi_last = np.minimum(last + 1, _GRID_MAX)[:, None]
        if m == 1:
            return lo_last, hi_last, np.ones_like(lo_last, dtype=bool)
        head = cells[:, None, :m - 1] + self._offs[None, :, :]       # [n, k, m-1]
        valid = ((head >= 0) & (head <= _GRID_MAX)).all(axis=2)
        base = (head << self._shift[None, None, :m - 1]).sum(axis=2)
        return base + lo_last, base + hi_last, valid

    @staticmethod
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

    def _query_chunks(self, cnt: np.ndarray):
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

    def candidates_of(self, z: np.ndarray):
        """Yield (query, id) arrays of alive stored identities in neighbour cells (chunked)."""
        n = len(z)
        if n == 0 or self.ntotal == 0:
            return
        lo_c, hi_c, valid = self._ranges(self._cells(z))
        levels = [(c, i, zz) for c, i, zz in ((self.codes, self.ids, self.zs),
                                              (self.scodes, self.sids, self.szs)) if len(c)]
        spans = self._lookup([c for c, _, _ in levels], lo_c, hi_c, valid)
        cnt = sum((hi - lo).sum(axis=1) for lo, hi in spans)
        self.scanned += int(cnt.sum())
        for s, e in self._query_chunks(cnt):
            qs, cs = [], []
            for (codes, ids, zz), (lo, hi) in zip(levels, spans):
                row, pos = _expand(lo[s:e], hi[s:e])
                q = s + row // lo.shape[1]
                near = self._near(z[q], zz[pos])
                qs.append(q[near])
                cs.append(ids[pos[near]])
            q, c = np.concatenate(qs), np.concatenate(cs)
            if self.stale and len(c):
                ok = self._alive(c)
                q, c = q[ok], c[ok]
            yield q, c

    def _batch_pairs(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (i, j), j < i, of batch items in neighbour cells (a superset of similar pairs)."""
        n = len(z)
        codes = self._code(z)
        order = np.argsort(codes, kind="stable")
        sc = codes[order]
        lo_c, hi_c, valid = self._ranges(self._cells(z))
        (lo, hi), = self._lookup([sc], lo_c, hi_c, valid)
        cnt = (hi - lo).sum(axis=1) - 1  # minus the item itself
        self.scanned += int(cnt.sum())
        if int(cnt.sum()) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pis, pjs = [], []
        for s, e in self._query_chunks(cnt + 1):
            row, pos = _expand(lo[s:e], hi[s:e])
            i = s + row // lo.shape[1]
            j = order[pos]
            keep = j < i
            i, j = i[keep], j[keep]
            keep = self._near64(z[i], z[j])
            pis.append(i[keep])
            pjs.append(j[keep])
        return np.concatenate(pis), np.concatenate(pjs)

    def resolve(self, keys: np.ndarray, z: np.ndarray, key_fn=None) -> ResolveResult:
        """Decide, exactly and as if sequentially, what each transition of a batch joins."""
        n = len(keys)
        delta = self.delta
        existing = np.full(n, -1, dtype=np.int64)
        best_d = np.full(n, np.inf)
        checked = 0
        step = max(1, _EXACT_CHUNK_VALUES // max(1, self.key_dim))
        for q, cand in self.candidates_of(z):
            if not len(cand):
                continue
            uniq, inv = np.unique(cand, return_inverse=True)
            ukeys = self._keys_of(uniq)
            dist = np.empty(len(cand))
            for s in range(0, len(cand), step):
                dist[s:s + step] = exact_sq_dist(keys[q[s:s + step]], ukeys[inv[s:s + step]])
            checked += len(cand)
            ok = dist <= delta
            if ok.any():
                q, c, d = q[ok], cand[ok], dist[ok]
                order = np.lexsort((c, d, q))  # by query, then distance, then id
                q, c, d = q[order], c[order], d[order]
                first = np.ones(len(q), dtype=bool)
                first[1:] = q[1:] != q[:-1]
                q, c, d = q[first], c[first], d[first]
                better = d < best_d[q]  # chunks hold disjoint queries; kept for safety
                existing[q[better]] = c[better]
                best_d[q[better]] = d[better]
        batch = np.full(n, -1, dtype=np.int64)
        if n > 1:
            pi, pj = self._batch_pairs(z)
            checked += len(pi)
            batch = _sequential_batch(keys, pi, pj, existing, best_d, delta, step)
        return ResolveResult(existing, batch, checked)


def _sequential_batch(keys, pi, pj, existing, best_d, delta, step) -> np.ndarray:
    """Within-batch joins, as if the batch were stored one transition at a time.

    Vectorised first: exact distances of every candidate pair; only pairs within delta whose
    earlier item j matched no existing identity (so it may create one) and that are strictly
    nearer than i's best existing match can change a decision. Only the items i of those pairs
    go through the sequential pass (in increasing i, so j's own decision is final when i is
    visited)."""
    n = len(keys)
    batch = np.full(n, -1, dtype=np.int64)
    if not len(pi):
        return batch
    keep = existing[pj] < 0
    pi, pj = pi[keep], pj[keep]
    if not len(pi):
        return batch
    d = np.empty(len(pi))
    for s in range(0, len(pi), step):
        d[s:s + step] = exact_sq_dist(keys[pi[s:s + step]], keys[pj[s:s + step]])
    keep = (d <= delta) & (d < best_d[pi])
    pi, pj, d = pi[keep], pj[keep], d[keep]
    if not len(pi):
        return batch
    order = np.lexsort((pj, d, pi))  # by i, then distance, then earliest j
    pi, pj, d = pi[order], pj[order], d[order]
    creates = existing < 0
    starts = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    ends = np.r_[starts[1:], len(pi)]
    for s, e in zip(starts.tolist(), ends.tolist()):
        i = int(pi[s])
        js = pj[s:e]
        ok = creates[js]
        if not ok.any():
            continue
        k = int(np.flatnonzero(ok)[0])  # nearest (then earliest) partner that created an identity
        existing[i] = -1
        best_d[i] = d[s + k]
        batch[i] = js[k]
        creates[i] = False
    return batch
