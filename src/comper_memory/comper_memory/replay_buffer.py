"""MemoryReplayBuffer: the memory service as a plain replay buffer for any Python learner.

numpy in, numpy out; no ROS types in its interface::

    from comper_memory.replay_buffer import MemoryReplayBuffer

    with MemoryReplayBuffer("memory_node", seed=0) as buffer:  # a running memory_node
        buffer.add(obs, action, reward, next_obs, terminated, truncated)
        buffer.extend(obs_batch, action_batch, ...)             # [N, ...] arrays
        if len(buffer) >= 64:
            b = buffer.sample(64)                               # dict of numpy arrays
            loss = td_loss(b["obs"], b["action"], b["reward"], b["next_obs"], b["terminated"])

What it does with the memory (docs/memory-service.md, "The memory as a replay buffer"):

- **A sample sees every transition added before it.** The memory groups similar transitions
  (squared distance of [s, a, r, s'] <= the node's ``delta``) into one identity; new and grown sets
  wait in TM until a reduction makes each one RTM entry, and RTM is what is sampled. The node's
  ``~/reduce`` pops at most ``max_sets`` sets per call, so before it draws the buffer reduces
  *until TM is empty*: it calls ``~/reduce`` again as long as a call reduced as many sets as it
  was allowed. Chosen over a draw across TM and RTM because a grown set sits in both (it would
  count twice) and the two carry different labels (newest label in TM, prediction in RTM); after
  the reduction every identity is one RTM entry with its prediction, and a draw stays uniform over
  identities. Sets another reducer holds under a lease (a QT trainer's, in flight) are in neither
  table until it commits them.
- A draw is uniform over *identities*, not over transitions: near-duplicates count once, which is
  the compact memory's point. With continuous states and the default delta 1e-4 practically every
  transition is its own identity and the buffer behaves as a uniform one.
- **Batched stores and prefetched draws.** ``add`` / ``extend`` collect transitions and send one
  ``~/store`` per ``store_every`` (default 64) in a background thread; the learner does not wait
  for the answer. With ``prefetch`` > 0 (default 32; fewer when they would hold more than 64 MiB
  of observations) the background thread fetches ``prefetch`` batches in one request (store what
  is collected, reduce until TM is empty, draw) while the learner uses the previous ones; the next
  such request is sent when a fetched set of batches starts being used, so it covers every
  transition added up to then. Exactness: each batch was drawn from the
  N entries the memory held when it was requested; the m transitions added since (stored or not)
  are mixed in locally, each as one more entry: the number of them in a batch of k is drawn from
  the hypergeometric law (m of N + m entries, k draws without replacement) and that many rows of
  the batch, at random positions, are replaced by distinct ones of the m. That is exactly a uniform
  draw of k distinct entries out of N + m, so no transition added before a sample is missed. The one
  difference to a draw after reducing: a recent transition that the memory merges into an existing
  identity (within delta of it) counts as its own entry until the next fetch covers it; such rows,
  and all rows of recent transitions, carry ``identity_id`` ``PENDING_IDENTITY`` and ``count`` 1
  (the memory has not answered for them yet). ``prefetch=0`` draws every batch in its own request
  after storing and reducing (no local mixing; one wait per sample). Other learners' transitions
  reach a prefetched batch from the next fetch on.
- **Reproducible from a seed.** ``seed`` starts a numpy Generator of this buffer: every request
  carries a seed drawn from it (the node draws with ``numpy.random.default_rng(seed)``), and the
  local mixing draws from it too. With the same seed, the same transitions added in the same order
  and a memory that holds nothing else (a fresh node), the batches are the same, run after run.
  ``seed=None``: the node's own generator (its ``sample_seed``) and an entropy-seeded local one.
  ``sample(k, seed=s)`` is one reproducible draw from the memory as it is now (stored, reduced,
  drawn with seed s; no prefetch, the stream is left as it was).
- ``len(buffer)`` is the number of live identities (the memory's ``identities``); the memory's
  ``rtm_capacity`` and ``tm_capacity`` bound it (least recently updated identities are evicted).
- **Labels are optional.** COMPER and COMCACT store a value label with each transition (the
  bootstrap value Q(s', .) of the learner, 0 when terminated) and read it back as QT's target. A
  learner that gives none gets ``default_label`` (0.0) stored. The memory node's own reduction
  predicts each set's newest label, so ``sample()["label"]`` is then that constant: harmless for a
  learner that computes its own targets (DQN, DDPG, TD3, SAC: the labels are never read), but a
  learner that wants QT's targets from this memory must give real labels and reduce through the QT
  trainer node instead.
- Errors: bad input raises ValueError in ``add`` / ``extend``, before anything is kept (a
  transition whose shapes or dtypes differ from this buffer's first one included). A store the
  node refuses in the background (e.g. shapes that differ from what another client stored) raises
  MemoryServiceError at this buffer's next ``sample``, ``flush``, ``len``, ``stats`` or ``close``;
  the refused batch is not stored at all.

Several learners (or actors and a learner) may share one memory node; the node's rate limiter
(``samples_per_insert``) holds them to a ratio, and ``store``/``sample`` then wait in this client
(``rate_limit_timeout``); a prefetch of ``prefetch`` batches counts as that many samples when it is
fetched, so with a ratio set give ``rate_error_buffer`` room for it or use ``prefetch=0``.

Size: one class whose parts share one piece of state: the background worker that stores and prefetches, the
transitions added since the last fetch (``_Recent``), and the sampler that mixes those into a prefetched batch as
an exact uniform draw; split apart, each would have to reach into the others' bookkeeping.
"""
from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from comper_msgs_py.arrays import Transitions

from .client import MemoryClient

__all__ = ["MemoryReplayBuffer", "DEFAULT_LABEL", "DEFAULT_STORE_EVERY", "DEFAULT_PREFETCH", "PENDING_IDENTITY"]

#: the value label stored for a transition a learner gives none for (module text)
DEFAULT_LABEL = 0.0
#: transitions collected per store call (module text)
DEFAULT_STORE_EVERY = 64
#: batches fetched per request (module text)
DEFAULT_PREFETCH = 32
#: ``identity_id`` of a sampled row that is a transition added since its batch was fetched (module text)
PENDING_IDENTITY = np.iinfo(np.uint64).max
#: sets one ~/reduce call may pop while the buffer reduces until TM is empty (at least; more when more were stored)
REDUCE_CHUNK = 4096
#: rows one fetch may ask for (the node's default max_sample_batch); fewer batches are fetched for large ones
MAX_FETCH_ROWS = 65536
#: bytes of observations one fetch may bring (frames: fewer batches per fetch)
MAX_FETCH_BYTES = 64 << 20

_COLUMNS = ("obs", "action", "reward", "next_obs", "terminated", "truncated", "label")


def _obs_array(x) -> np.ndarray:
    """Observations as the memory keeps them: uint8 frames as they are, anything else float32."""
    x = np.asarray(x)
    return x if x.dtype == np.uint8 else x.astype(np.float32, copy=False)


def _columns(t: Transitions) -> dict:
    return {"obs": t.states, "action": t.actions, "reward": t.rewards, "next_obs": t.next_states,
            "terminated": t.terminated, "truncated": t.truncated, "label": t.value_labels}


@dataclass
class _Fetch:
    """Batches drawn in one request: ``num_batches`` x ``k1`` rows out of ``population`` entries, covering the
    transitions this buffer added before ``cover``."""
    cover: int
    k: int
    population: int
    k1: int
    num_batches: int
    rows: dict | None        # the columns of _COLUMNS plus identity_id and count; None when k1 == 0
    used: int = 0


class _Recent:
    """The transitions added since a sequence number, in growable arrays, for mixing into fetched batches."""

    def __init__(self) -> None:
        self.base = 0          # sequence number of row 0
        self.n = 0
        self.cols: dict | None = None

    def append(self, cols: dict, first: int) -> None:
        k = len(cols["reward"])
        if self.n == 0:
            self.base = first
        if self.cols is None or self.n + k > len(self.cols["reward"]):
            cap = max(64, 2 * (self.n + k))
            grown = {c: np.empty((cap, *v.shape[1:]), v.dtype) for c, v in cols.items()}
            if self.cols is not None:
                for c in grown:
                    grown[c][:self.n] = self.cols[c][:self.n]
            self.cols = grown
        for c, v in cols.items():
            self.cols[c][self.n:self.n + k] = v
        self.n += k

    def take(self, seqs: np.ndarray) -> dict:
        idx = np.asarray(seqs, np.int64) - self.base
        return {c: v[idx] for c, v in self.cols.items()}

    def keep_from(self, seq: int) -> None:
        """Forget the rows before sequence number ``seq``."""
        drop = min(max(0, seq - self.base), self.n)
        if drop == 0:
            return
        self.n -= drop
        if self.n:
            for v in self.cols.values():
                v[:self.n] = v[drop:drop + self.n].copy()
        self.base += drop


class MemoryReplayBuffer:
    """A replay buffer backed by a memory node (module text).

    memory: a MemoryClient, or the memory node's name (a standalone client is then created and
    closed with the buffer). store_every: transitions collected per store call, sent in the background
    (a sample mixes in what is not stored yet). prefetch: batches fetched per request (0: one request
    per sample, no local mixing). seed: this buffer's sampling stream (None: the node's generator).
    default_label: the label stored when ``add``/``extend`` get none. source: ``rtm`` (reduce, then
    sample the reduced memory; the default) or ``tm`` (sample the not-yet-reduced sets and never
    reduce: the COMPER-M ablation's view). run_id: written with the transitions (bags, provenance)."""

    def __init__(self, memory: MemoryClient | str = "memory_node", *, store_every: int = DEFAULT_STORE_EVERY,
                 prefetch: int = DEFAULT_PREFETCH, seed: int | None = None, default_label: float = DEFAULT_LABEL,
                 source: str = "rtm", run_id: str = "", timeout: float = 30.0, wait_for_service_s: float = 30.0):
        if source not in ("rtm", "tm"):
            raise ValueError(f"source must be 'rtm' or 'tm', got {source!r}")
        if store_every < 1:
            raise ValueError(f"store_every must be >= 1, got {store_every}")
        if prefetch < 0:
            raise ValueError(f"prefetch must be >= 0, got {prefetch}")
        if seed is not None and not 0 <= int(seed) < 2**63:
            raise ValueError(f"seed must be None or in [0, 2**63), got {seed}")
        if not np.isfinite(default_label):
            raise ValueError(f"default_label must be finite, got {default_label}")
        self._worker: ThreadPoolExecutor | None = None
        self._owned = isinstance(memory, str)
        self.memory = MemoryClient.standalone(memory, timeout=timeout) if self._owned else memory
        if wait_for_service_s > 0 and not self.memory.wait_for_service(wait_for_service_s):
            name = self.memory.memory_node
            self.close()
            raise RuntimeError(f"no memory node {name!r} answered within {wait_for_service_s:g} s "
                               f"(start one with: ros2 run comper_memory memory_node --ros-args -r __node:={name})")
        self.store_every = int(store_every)
        self.prefetch = int(prefetch)
        self.seed = None if seed is None else int(seed)
        self.default_label = float(default_label)
        self.source = source
        self.run_id = run_id
        self._rng = np.random.default_rng(self.seed)
        self._schema: tuple | None = None   # (obs shape, obs dtype, action shape, action dtype) of the first add
        self._pending: list[Transitions] = []
        self._pending_n = 0
        self._recent = _Recent()
        self._stores: list[Future] = []     # store calls sent and not yet checked
        self._current: _Fetch | None = None  # the fetched batches in use
        self._next: Future | None = None     # the next fetch, in flight
        self._next_k = 0
        self._unreduced = 0        # transitions stored since this buffer's last reduction (worker thread only)
        self.added = 0             # transitions given to add / extend
        self.fetches = 0           # requests that drew batches (each: store, reduce until TM is empty, sample)
        # every call to the node runs in this one thread, in the order the learner asked for them
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="memory_replay_buffer")

    # --- writing ------------------------------------------------------------------------------
    def add(self, obs, action, reward, next_obs, terminated, truncated=False, label=None) -> None:
        """One transition (arrays without a batch dimension)."""
        self.extend(np.asarray(obs)[None], np.asarray(action)[None], np.asarray([reward]),
                    np.asarray(next_obs)[None], np.asarray([terminated]), np.asarray([truncated]),
                    None if label is None else np.asarray([label]))

    def extend(self, obs, action, reward, next_obs, terminated, truncated=None, label=None) -> None:
        """N transitions: obs/next_obs [N, *obs_shape], action [N, *action_shape], reward,
        terminated, truncated, label [N] (truncated None: all False; label None: default_label).
        Bad input raises ValueError here, before anything is kept or sent."""
        obs, next_obs = _obs_array(obs), _obs_array(next_obs)
        n = int(obs.shape[0]) if obs.ndim else 0
        if n == 0:
            return
        action = np.asarray(action)
        action = action.astype(np.int64) if action.dtype.kind in "iub" else action.astype(np.float32)
        reward = np.asarray(reward, np.float32).reshape(-1)
        lab = (np.full(n, self.default_label, np.float32) if label is None
               else np.asarray(label, np.float32).reshape(-1))
        t = Transitions(states=obs, actions=action, rewards=reward, next_states=next_obs,
                        terminated=np.asarray(terminated, bool).reshape(-1),
                        truncated=(np.zeros(n, bool) if truncated is None else np.asarray(truncated, bool).reshape(-1)),
                        value_labels=lab, run_id=self.run_id)
        t.validate(require_labels=True)
        schema = (t.obs_shape, t.states.dtype, t.actions.shape[1:], t.actions.dtype)
        if self._schema is None:
            self._schema = schema
        elif schema != self._schema:
            raise ValueError(f"transitions with observations {schema[0]} {schema[1]} and actions {schema[2]} "
                             f"{schema[3]} differ from this buffer's ({self._schema[0]} {self._schema[1]}, "
                             f"{self._schema[2]} {self._schema[3]})")
        self._pending.append(t)
        self._pending_n += n
        if self._current is not None or self._next is not None:   # a fetched batch may need them mixed in
            self._recent.append(_columns(t), self.added)
        self.added += n
        if self._pending_n >= self.store_every:
            self._send()

    def _send(self) -> None:
        """Send what add/extend collected (one store call, in the background)."""
        self._raise_store_errors()
        if not self._pending:
            return
        parts, self._pending, self._pending_n = self._pending, [], 0
        batch = parts[0] if len(parts) == 1 else Transitions.concatenate(parts)
        self._stores.append(self._submit(self._store_job, batch))

    def _store_job(self, batch: Transitions) -> None:
        self.memory.store(batch)
        self._unreduced += len(batch)

    def _raise_store_errors(self, wait: bool = False) -> None:
        """Raise the error of a background store that failed (wait: for every store sent)."""
        left, error = [], None
        for f in self._stores:
            if wait or f.done():
                exc = f.exception()
                if exc is not None and error is None:
                    error = exc
            else:
                left.append(f)
        self._stores = left
        if error is not None:
            raise error

    def flush(self) -> None:
        """Send what add/extend collected and wait until the memory has stored it (a refused store raises here)."""
        self._send()
        self._raise_store_errors(wait=True)

    def _submit(self, fn, *args) -> Future:
        if self._worker is None:
            raise RuntimeError("MemoryReplayBuffer: closed")
        return self._worker.submit(fn, *args)

    # --- reading ------------------------------------------------------------------------------
    def _reduce_all(self) -> int:
        """Reduce until TM is empty (worker thread); the RTM entries after it."""
        most = max(self._unreduced, REDUCE_CHUNK)
        while True:
            r = self.memory.reduce(max_sets=most)
            if r.sets_reduced < most:
                break
        self._unreduced = 0
        return int(r.rtm_size)

    def _fetch_job(self, k: int, num_batches: int, seed: int | None, cover: int) -> _Fetch:
        """(worker thread) After the stores sent before it: reduce until TM is empty, then draw num_batches
        batches of min(k, entries)."""
        population = self._reduce_all() if self.source == "rtm" else int(self.memory.stats()["tm_sets"])
        k1 = min(k, population)
        rows = None
        if k1:
            t, ids, counts = self.memory.sample(k1, self.source, seed, num_batches=num_batches)
            rows = {**_columns(t), "identity_id": ids, "count": counts}
        self.fetches += 1
        return _Fetch(cover, k, population, k1, num_batches, rows)

    def _request(self, k: int, num_batches: int, seed: int | None = None) -> Future:
        """Store what is collected and queue a fetch that covers every transition added so far."""
        self._send()
        if seed is None and self.seed is not None:
            seed = int(self._rng.integers(2**63))
        return self._submit(self._fetch_job, k, num_batches, seed, self.added)

    def sample(self, batch_size: int, seed: int | None = None, *, fill: bool = False) -> dict:
        """batch_size distinct identities, uniformly (module text): a dict of numpy arrays
        obs, action, reward, next_obs, terminated, truncated, label, identity_id, count.

        Fewer entries than batch_size: ValueError, or with fill=True every entry once and the rest
        of the batch drawn from them uniformly with replacement (what a buffer that samples with
        replacement, like Stable-Baselines3's, gives its learner early on). seed: one reproducible
        draw from the memory as it is now (module text)."""
        k = int(batch_size)
        if k < 1:
            raise ValueError(f"sample: batch_size must be >= 1, got {batch_size}")
        self._raise_store_errors()
        if seed is not None:
            return self._batch(self._request(k, 1, int(seed)).result(), 0, k, fill, np.random.default_rng(seed))
        if self.prefetch == 0:
            return self._batch(self._request(k, 1).result(), 0, k, fill, self._rng)
        cur = self._current
        if cur is None or cur.k != k or cur.used >= cur.num_batches:
            row = 2 * int(np.prod(self._schema[0])) * np.dtype(self._schema[1]).itemsize if self._schema else 0
            nb = max(1, min(self.prefetch, MAX_FETCH_ROWS // k, MAX_FETCH_BYTES // max(1, k * row)))
            nxt = self._next if self._next is not None and self._next_k == k else self._request(k, nb)
            self._next = None
            self._current = cur = nxt.result()
            # the next fetch is asked for now, while these batches are used: it covers what was added until now
            self._recent.keep_from(cur.cover)
            self._next, self._next_k = self._request(k, nb), k
        out = self._batch(cur, cur.used, k, fill, self._rng)
        cur.used += 1
        return out

    def _batch(self, f: _Fetch, i: int, k: int, fill: bool, rng: np.random.Generator) -> dict:
        """Batch i of a fetch, with the transitions added since it was asked for mixed in (module text)."""
        n, m, k1 = f.population, self.added - f.cover, f.k1
        if n + m < k and not fill:
            raise ValueError(f"sample: batch_size {k} exceeds the {n + m} entries of the memory "
                             f"({self.source.upper()}; use fill=True to repeat entries)")
        rows = {c: v[i * k1:(i + 1) * k1] for c, v in f.rows.items()} if k1 else None
        if m == 0 and k1 == k:
            return rows
        if n + m >= k:
            j = int(rng.hypergeometric(m, n, k)) if m else 0    # how many of the k are recent transitions
            if j == 0 and k1 == k:
                return rows
            recent = self._recent_rows(f.cover + rng.choice(m, j, replace=False))
            if k1 == k:        # the fetched rows are in random order: replace j of them at random positions
                out = {c: v.copy() for c, v in rows.items()}
                pos = rng.choice(k, j, replace=False)
                for c in out:
                    out[c][pos] = recent[c]
                return out
            keep = rng.choice(k1, k - j, replace=False) if k1 else np.zeros(0, np.int64)
            order = rng.permutation(k)
            return {c: np.concatenate([rows[c][keep], recent[c]])[order] if rows else recent[c][order]
                    for c in recent}
        # fill: every entry once, the rest of the batch drawn from them with replacement
        if n + m == 0:
            raise ValueError("sample: the memory holds no transitions yet")
        every = rows if m == 0 else self._recent_rows(f.cover + np.arange(m))
        if rows is not None and m:
            every = {c: np.concatenate([rows[c], every[c]]) for c in every}
        pick = np.concatenate([np.arange(n + m), rng.integers(0, n + m, k - n - m)])
        return {c: v[pick] for c, v in every.items()}

    def _recent_rows(self, seqs: np.ndarray) -> dict:
        """The rows of transitions added since a fetch (sequence numbers), as a fetched batch has them."""
        out = self._recent.take(seqs)
        out["identity_id"] = np.full(len(seqs), PENDING_IDENTITY, np.uint64)
        out["count"] = np.ones(len(seqs), np.uint32)
        return out

    def stats(self) -> dict:
        """The memory's MemoryStats as a dict, after everything added so far is stored."""
        self.flush()
        return self._submit(self.memory.stats).result()

    def __len__(self) -> int:
        """Live identities in the memory (after everything added so far is stored)."""
        return int(self.stats()["identities"])

    # --- life -------------------------------------------------------------------------------
    def close(self) -> None:
        """Send what is collected (if the node still answers), stop the background thread and close an
        owned client. Idempotent."""
        worker, self._worker = self._worker, None
        try:
            if worker is not None:
                try:
                    if self._next is not None:
                        self._next.cancel()            # not needed any more (runs on if it has started)
                    if self._pending and self.memory is not None:
                        parts, self._pending, self._pending_n = self._pending, [], 0
                        self._stores.append(worker.submit(self._store_job, Transitions.concatenate(parts)))
                    worker.shutdown(wait=True, cancel_futures=False)
                    self._next = self._current = None
                    self._raise_store_errors(wait=True)
                finally:
                    worker.shutdown(wait=True)
        finally:
            if self._owned and self.memory is not None:
                self.memory.close()
            self.memory = None if self._owned else self.memory

    def __enter__(self) -> "MemoryReplayBuffer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
