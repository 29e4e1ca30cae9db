"""Pure-Python core of the compact memory (no ROS imports).

Public API: :class:`MemoryConfig`, :func:`transition_keys`, :func:`exact_sq_dist`,
:class:`ExactIndex`, :class:`CompactMemory` with its results, and the storage errors.
"""
from .config import MemoryConfig
from .index import ExactIndex, ResolveResult
from .keys import exact_sq_dist, key_size_of, transition_keys
from .memory import (CommitResult, CompactMemory, LeaseError, MemoryInputError, ReductionLease,
                     SampleResult, StoreResult, newest_label)
from .rate_limiter import RateLimited, RateLimiter
from .storage import SnapshotError

__all__ = ["MemoryConfig", "transition_keys", "key_size_of", "exact_sq_dist", "ExactIndex",
           "ResolveResult", "CompactMemory", "MemoryInputError", "LeaseError", "StoreResult",
           "SampleResult", "ReductionLease", "CommitResult", "newest_label", "SnapshotError",
           "RateLimiter", "RateLimited"]
