"""The faiss engine of the similarity index: IVF over an orthonormal projection.

It proposes candidates only; :class:`~comper_memory.core.similarity.SimilarityIndex` re-checks
them in float64 and decides (the decision rule is in that module). Why no similar pair is
missed, with r = sqrt(delta):

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

import numpy as np

from .similarity import U32, KeySource, SimilarityIndex

faiss = None   # imported by the first ExactIndex: the default grid engine, and clients, never load it


def _load_faiss() -> None:
    global faiss
    if faiss is None:
        import faiss as module
        faiss = module

__all__ = ["ExactIndex"]

class ExactIndex(SimilarityIndex):
    """Exact radius-delta nearest-identity index on faiss IVF lists (see module docstring)."""

    engine = "ivf"

    def __init__(self, key_dim: int, delta: float, source: KeySource, *, projection_dim: int = 8,
                 min_train: int = 2048, list_size: int = 256, max_lists: int = 4096,
                 rebuild_growth: float = 4.0, seed: int = 0):
        _load_faiss()
        super().__init__(key_dim, delta, source)
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
        cast_err = U32 * (self.max_y_norm + 1.0)
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
        err = 4.0 * (self.m + 2) * U32 * (ysq + float(self._cnorm.max()) + 1.0)
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

    def reindex(self) -> None:
        """Index every live identity of the source anew (after a snapshot restore)."""
        ids = self.source.live_ids()
        for s, keys in self.key_blocks(ids, 1 << 24):
            self._add_faiss(ids[s:s + len(keys)], self.project(keys))
        self.maybe_rebuild(force=len(ids) >= self.min_train)

    def candidates_of(self, y: np.ndarray):
        """One chunk (query, id) of :meth:`candidates` (every query at once)."""
        lims, ids = self.candidates(y)
        if len(ids):
            yield np.repeat(np.arange(len(y)), np.diff(lims)), ids

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

    def batch_pairs(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
