"""The similarity index of the memory: the engine choice and the names the rest of the suite uses.

* :mod:`.similarity` -- the interface (:class:`SimilarityIndex`, :class:`KeySource`) and the one
  exact, as-if-sequential decision (``resolve``) every engine shares;
* :mod:`.index_grid` -- :class:`GridIndex`, sorted cell codes over a PCA projection (numpy,
  the default: it measured faster at every key size, see docs/memory.md);
* :mod:`.index_faiss` -- :class:`ExactIndex`, faiss IVF lists over an orthonormal projection.

Engines only propose candidates; decisions are identical whichever one runs.
"""
from __future__ import annotations

from .config import MemoryConfig
from .index_faiss import ExactIndex
from .index_grid import GridIndex
from .similarity import KeySource, ResolveResult, SimilarityIndex

__all__ = ["ExactIndex", "GridIndex", "KeySource", "ResolveResult", "SimilarityIndex", "make_index"]

_ENGINES = {"grid": "grid", "faiss_ivf": "ivf"}


def make_index(config: MemoryConfig, key_dim: int, source: KeySource,
               engine: str | None = None) -> SimilarityIndex:
    """The index ``config.index_engine`` names ('grid' | 'faiss_ivf'); ``engine`` ('grid' | 'ivf'),
    set by tests and benchmarks, overrides it."""
    c = config
    if (engine or _ENGINES[c.index_engine]) == "grid":
        return GridIndex(key_dim, c.delta, source, grid_dims=min(3, c.index_projection_dim),
                         filter_dims=c.index_projection_dim, min_train=c.index_min_train,
                         rebuild_growth=c.index_rebuild_growth, seed=c.index_seed)
    return ExactIndex(key_dim, c.delta, source, projection_dim=c.index_projection_dim,
                      min_train=c.index_min_train, list_size=c.index_list_size,
                      max_lists=c.index_max_lists, rebuild_growth=c.index_rebuild_growth,
                      seed=c.index_seed)
