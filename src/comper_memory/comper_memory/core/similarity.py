"""The similarity-index interface and the exact decision every engine shares.

Decision rule (method.md section 1): a store of n transitions is processed as if sequentially;
transition i joins the nearest live identity whose key is within ``delta`` (squared L2, computed
exactly in float64 by :func:`~comper_memory.core.keys.exact_sq_dist`; ties -> lowest identity id),
which may be an identity created by an earlier transition of the same batch; otherwise it
creates a new identity. Identity ids are allocated in increasing order, so "lowest id" is also
"oldest", and an existing identity wins a tie against one created in the same batch.

:meth:`SimilarityIndex.resolve` applies that rule once for every engine. An engine (faiss IVF in
``index_faiss``, the sorted-cell grid in ``index_grid``) only proposes candidates: a superset of
the stored identities within delta of each query (``candidates_of``) and of the pairs inside the
batch within delta (``batch_pairs``). Every proposal is re-checked here against the full keys in
float64, so the engine affects speed only, never a decision.

The index never owns keys: it reads them through a :class:`KeySource` (the memory's slot table),
which reconstructs each identity's key from its stored representative.
"""
from __future__ import annotations

from typing import Iterator, Protocol

import numpy as np

from .keys import exact_sq_dist

__all__ = ["KeySource", "ResolveResult", "SimilarityIndex"]

U32 = float(np.finfo(np.float32).eps)  # 1.19e-7 (2 x unit roundoff, conservative)
SUBSPACE = 64  # keys longer than this are projected through a random orthonormal 64-d subspace first
_EXACT_CHUNK_VALUES = 1 << 22  # float64 values per exact re-check chunk (32 MiB)


class KeySource(Protocol):
    """What an index may ask of the store that owns the keys."""

    def live_ids(self) -> np.ndarray:
        """Live identity ids, increasing."""

    def keys_of(self, ids: np.ndarray) -> np.ndarray:
        """float32 keys [n, D] of live identities."""

    def alive(self, ids: np.ndarray) -> np.ndarray:
        """bool [n]: which ids are still live (engines with lazy removal filter with it)."""


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


class SimilarityIndex:
    """Exact radius-delta nearest-identity index: engines subclass it and provide candidates.

    An engine implements ``project(keys)`` (the points it partitions, fixed on first use),
    ``add(ids, y)``, ``remove(ids)``, ``reindex()`` (index every live identity of the source
    anew, after a snapshot restore), ``candidates_of(y)``, ``batch_pairs(y)``, ``ntotal``,
    ``nlist`` and ``bytes_used()``."""

    engine = ""

    def __init__(self, key_dim: int, delta: float, source: KeySource):
        self.key_dim = int(key_dim)
        self.delta = float(delta)
        self.r = float(np.sqrt(self.delta))
        self.source = source

    def key_blocks(self, ids: np.ndarray, values: int) -> Iterator[tuple[int, np.ndarray]]:
        """(start, keys) of ``ids`` in row blocks of at most ``values`` key values (at least one
        row): re-indexing reads the live keys this way, never all of them at full width at once."""
        step = max(1, values // max(1, self.key_dim))
        for s in range(0, len(ids), step):
            yield s, self.source.keys_of(ids[s:s + step])

    def candidates_of(self, y: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Yield (query, id) arrays: a superset of the live stored identities within delta of each
        query (a chunk holds each of its queries' candidates once; a query may recur in a later chunk)."""
        raise NotImplementedError

    def batch_pairs(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (i, j), j < i, of batch items: a superset of the pairs within delta."""
        raise NotImplementedError

    def resolve(self, keys: np.ndarray, y: np.ndarray) -> ResolveResult:
        """Decide, exactly and as if sequentially, what each transition of a batch joins.

        keys: float32 [n, D] batch keys; y: their projections (from ``project``)."""
        n = len(keys)
        delta = self.delta
        existing = np.full(n, -1, dtype=np.int64)
        best_d = np.full(n, np.inf)
        checked = 0
        step = max(1, _EXACT_CHUNK_VALUES // max(1, self.key_dim))
        for q, cand in self.candidates_of(y):
            if not len(cand):
                continue
            uniq, inv = np.unique(cand, return_inverse=True)
            ukeys = self.source.keys_of(uniq)
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
                # a query may come back in a later chunk (the grid engine's wide keys): nearer,
                # or as near with a lower id, wins
                better = (d < best_d[q]) | ((d == best_d[q]) & (c < existing[q]))
                existing[q[better]] = c[better]
                best_d[q[better]] = d[better]
        batch = np.full(n, -1, dtype=np.int64)
        if n > 1:
            pi, pj = self.batch_pairs(y)
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
