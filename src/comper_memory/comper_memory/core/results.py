"""What the memory's operations return, and the errors they raise (no state here)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from comper_msgs_py.arrays import Transitions

__all__ = ["MemoryInputError", "LeaseError", "StoreResult", "SampleResult", "ReductionLease",
           "CommitResult", "newest_label", "empty_transitions"]


class MemoryInputError(ValueError):
    """A request to the memory is invalid; nothing was changed."""


class LeaseError(MemoryInputError):
    """A reduction lease is unknown, already committed or expired; nothing was changed. Its message holds
    :data:`LEASE_GONE`, which is how a client across ROS (the QT trainer) tells this refusal from others."""


#: the words of every LeaseError message (the memory node forwards exception messages to clients)
LEASE_GONE = "is unknown, already committed or expired"


@dataclass
class StoreResult:
    identity_ids: np.ndarray   # int64 [N]: identity each transition joined or created
    new_identities: int        # identities created by this store
    similarity_hits: int       # transitions that joined an existing (or same-batch) identity
    evicted: int               # identities evicted to respect the capacities
    wal_sequence: int


@dataclass
class SampleResult:
    transitions: Transitions   # representatives; value_labels = QT prediction (RTM) / newest label (TM)
    identity_ids: np.ndarray   # int64 [k]
    counts: np.ndarray         # int64 [k]: transitions that joined each identity
    source: str


@dataclass
class ReductionLease:
    """Phase 1 of a two-phase reduction: the sets leased from TM (in the memory, and as a client
    receives them from ``reduce_begin``: ids uint64 and lengths uint32 there, no expiry)."""
    reduction_id: int
    identity_ids: np.ndarray        # int64 [k], TM order (oldest first)
    representatives: Transitions    # value_labels = newest label of each set
    label_history: np.ndarray       # float32 [sum(history_lengths)], per set oldest -> newest
    history_lengths: np.ndarray     # int64 [k]
    counts: np.ndarray              # int64 [k]
    expires_at: float = math.inf    # clock() time after which the lease is void (kept by the memory)

    def __len__(self) -> int:
        return int(self.identity_ids.shape[0])

    def histories(self) -> list[np.ndarray]:
        """One float32 array per set, oldest label first."""
        if not len(self):
            return []
        return np.split(self.label_history, np.cumsum(np.asarray(self.history_lengths, np.int64))[:-1])


@dataclass
class CommitResult:
    reduction_id: int
    upserted: int   # RTM entries written
    skipped: int    # identities evicted while leased
    wal_sequence: int


def newest_label(lease: ReductionLease) -> np.ndarray:
    """Built-in predictor for users without a QT: each set's newest value label."""
    return lease.representatives.value_labels.astype(np.float32, copy=True)


def empty_transitions(schema: dict | None) -> Transitions:
    """A batch of no transitions, shaped like the memory's (or a placeholder before any store)."""
    if schema is None:
        return Transitions(np.zeros((0, 0), np.float32), np.zeros(0, np.int64), np.zeros(0, np.float32),
                           np.zeros((0, 0), np.float32), np.zeros(0, bool), np.zeros(0, bool),
                           value_labels=np.zeros(0, np.float32))
    obs = (0,) + tuple(schema["obs_shape"])
    return Transitions(np.zeros(obs, np.dtype(schema["obs_dtype"])),
                       np.zeros((0,) + tuple(schema["action_shape"]), np.dtype(schema["action_dtype"])),
                       np.zeros(0, np.float32), np.zeros(obs, np.dtype(schema["obs_dtype"])),
                       np.zeros(0, bool), np.zeros(0, bool), value_labels=np.zeros(0, np.float32),
                       episode_ids=np.zeros(0, np.uint64), steps=np.zeros(0, np.uint64))
