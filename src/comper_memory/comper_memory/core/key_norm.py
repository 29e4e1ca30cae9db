"""KeyNormaliser: per-dimension standardisation of transition keys before every similarity decision.

With ``key_normalisation: none`` (the thesis) keys are [s, a, r, s'] as they come. With ``running``
each key dimension is mapped to (x - mean) / scale, where mean and scale are the running mean and
standard deviation of every key stored so far, *frozen* between updates so that all keys in the
index are on one scale:

* every applied store adds its raw keys to the running moments (count, mean, M2; Chan et al.'s
  pairwise merge in float64);
* at a committed reduction, once the moments cover ``key_norm_growth`` times the keys they covered
  at the last freeze (first: any), the frozen mean and scale are replaced and the memory re-indexes
  every identity with the new keys (so a run of n stores re-indexes about log(n) / log(growth)
  times);
* a dimension whose standard deviation is below ``key_norm_min_std`` keeps scale 1 (a constant
  reward, a padding value), so it never divides by ~0.

With ``delta_rule: nn_quantile`` (either mode) every freeze also divides the map by one factor g chosen so that
``delta`` sits at the ``delta_quantile`` quantile of the squared nearest-neighbour distances between live
identities: up to NN_QUERIES identities, evenly spread over the ids, each with its nearest among up to NN_REFS
(fewer for long keys) of them, measured on the keys as standardised so far. Dividing every key by g is the same as
multiplying ``delta`` by g^2, so the index and its exactness are unchanged; the rule only decides the scale, and it
follows the keys' spread as they grow (sets form at every budget). Its first freeze waits for NN_MIN_IDENTITIES
live identities (a handful of keys says nothing of their spread).

Before the first freeze the frozen map is the identity (mean 0, scale 1). Stores and commits are
what the write-ahead log replays, so a recovered memory rebuilds the same moments and freezes; a
snapshot holds them (:meth:`arrays` / :meth:`load`). ``delta`` is then a squared distance in
standard deviations (summed over the key's dimensions). Pure numpy; not thread-safe (the memory's
lock is held).
"""
from __future__ import annotations

import numpy as np

from .keys import sq_dist_matrix

__all__ = ["KeyNormaliser", "KEY_NORM_MODES", "DELTA_RULES", "nn_quantile_scale", "resolve_store"]

KEY_NORM_MODES = ("none", "running")
DELTA_RULES = ("fixed", "nn_quantile")
NN_QUERIES, NN_REFS, NN_REF_VALUES, NN_MIN_IDENTITIES = 1024, 4096, 1 << 24, 256


def resolve_store(index, key_norm: "KeyNormaliser", raw_keys: np.ndarray):
    """(projections, ResolveResult) of a store's raw keys: what a live store and its WAL replay both decide
    on, so the two cannot scale keys differently."""
    keys = key_norm.apply(raw_keys)
    y = index.project(keys)
    return y, index.resolve(keys, y)


def nn_quantile_scale(keys: np.ndarray, delta: float, quantile: float) -> float:
    """g such that delta is the ``quantile`` of the squared nearest-neighbour distances among ``keys / g`` (rows
    ordered by id): NN_QUERIES rows evenly spread, each against every other row. 1.0 when that quantile is 0."""
    x = np.asarray(keys, np.float64)
    q = np.unique(np.linspace(0, len(x) - 1, min(len(x), NN_QUERIES)).astype(np.int64))
    d2 = np.maximum(sq_dist_matrix(x[q], x), 0.0)
    d2[np.arange(len(q)), q] = np.inf
    dq = float(np.quantile(d2.min(1), quantile))
    return float(np.sqrt(dq / delta)) if dq > 0 and delta > 0 else 1.0


class KeyNormaliser:
    """Frozen per-dimension (mean, scale) applied to keys, and the running moments behind them."""

    def __init__(self, mode: str = "none", growth: float = 2.0, min_std: float = 1e-6, delta_rule: str = "fixed",
                 delta: float = 0.0, delta_quantile: float = 0.1):
        if mode not in KEY_NORM_MODES:
            raise ValueError(f"key_normalisation must be one of {', '.join(KEY_NORM_MODES)}, got {mode!r}")
        if delta_rule not in DELTA_RULES:
            raise ValueError(f"delta_rule must be one of {', '.join(DELTA_RULES)}, got {delta_rule!r}")
        self.mode, self.growth, self.min_std = mode, float(growth), float(min_std)
        self.delta_rule, self.delta, self.delta_quantile = delta_rule, float(delta), float(delta_quantile)
        self.reset()

    @property
    def enabled(self) -> bool:
        return self.mode == "running" or self.delta_rule == "nn_quantile"

    def reset(self) -> None:
        self.mean = self.scale = None      # frozen map (None: identity)
        self.n = 0                         # keys in the running moments
        self.mu = self.m2 = None           # running mean and sum of squared deviations, float64
        self.frozen_n = 0                  # keys the frozen map was computed from
        self.updates = 0                   # freezes so far

    def apply(self, keys: np.ndarray) -> np.ndarray:
        """Keys as the index sees them: (keys - mean) / scale in float32 (keys unchanged when off
        or before the first freeze). A deterministic function of the key, so equal keys stay equal."""
        if self.mean is None:
            return keys
        return ((np.asarray(keys, dtype=np.float64) - self.mean) / self.scale).astype(np.float32)

    def observe(self, raw_keys: np.ndarray) -> None:
        """Add applied raw keys [n, d] to the running moments (the frozen map does not change)."""
        if not self.enabled or len(raw_keys) == 0:
            return
        x = np.asarray(raw_keys, dtype=np.float64)
        nb = len(x)
        mb = x.mean(axis=0)
        m2b = ((x - mb) ** 2).sum(axis=0)
        if self.n == 0:
            self.n, self.mu, self.m2 = nb, mb, m2b
            return
        n = self.n + nb
        d = mb - self.mu
        self.mu = self.mu + d * (nb / n)
        self.m2 = self.m2 + m2b + d * d * (self.n * nb / n)
        self.n = n

    def maybe_freeze(self, live_keys=None) -> bool:
        """At a committed reduction: replace the frozen map when the moments have grown enough;
        True when it changed (the caller re-indexes). ``live_keys(k)``: raw keys of up to k live identities
        evenly spread over the ids (the nn_quantile rule's sample)."""
        if not self.enabled or self.n < 2 or (self.frozen_n and self.n < self.growth * self.frozen_n):
            return False
        if self.mode == "running":
            std = np.sqrt(self.m2 / self.n)
            mean, scale = self.mu.copy(), np.where(std < self.min_std, 1.0, std)
        else:
            mean, scale = np.zeros_like(self.mu), np.ones_like(self.mu)
        if self.delta_rule == "nn_quantile":
            sample = live_keys(min(NN_REFS, max(NN_MIN_IDENTITIES, NN_REF_VALUES // len(mean))))
            if len(sample) < NN_MIN_IDENTITIES:
                return False
            scale = scale * nn_quantile_scale((np.asarray(sample, np.float64) - mean) / scale, self.delta,
                                              self.delta_quantile)
        self.mean, self.scale = mean, scale
        self.frozen_n = self.n
        self.updates += 1
        return True

    def stats(self) -> dict:
        """What the memory's stats report of the normaliser."""
        return {"key_norm_updates": self.updates, "key_norm_keys": self.frozen_n}

    def arrays(self) -> dict[str, np.ndarray]:
        """Snapshot arrays (empty when off)."""
        if not self.enabled:
            return {}
        d = 0 if self.mu is None else len(self.mu)
        frozen = self.mean is not None
        moments = np.zeros((2, d), np.float64)
        if d:
            moments[0], moments[1] = self.mu, self.m2
        return {"key_norm_mean": self.mean if frozen else np.zeros(0), "key_norm_scale":
                self.scale if frozen else np.zeros(0), "key_norm_moments": moments,
                "key_norm_counts": np.array([self.n, self.frozen_n, self.updates], np.int64)}

    def load(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore from :meth:`arrays` (a snapshot without them: a fresh normaliser)."""
        self.reset()
        if not self.enabled or "key_norm_counts" not in arrays:
            return
        self.n, self.frozen_n, self.updates = (int(v) for v in arrays["key_norm_counts"])
        mom = np.asarray(arrays["key_norm_moments"], np.float64)
        if self.n:
            self.mu, self.m2 = mom[0].copy(), mom[1].copy()
        if len(arrays["key_norm_mean"]):
            self.mean = np.asarray(arrays["key_norm_mean"], np.float64).copy()
            self.scale = np.asarray(arrays["key_norm_scale"], np.float64).copy()
