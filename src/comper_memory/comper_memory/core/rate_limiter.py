"""RateLimiter: how fast the memory may be sampled relative to how fast it is filled (no ROS).

The vocabulary is Reverb's (``reverb.rate_limiters``): a *minimum size to sample* and a
*samples-per-insert* ratio held within an *error buffer*. Every transition stored is one insert,
every row a sample call returns (batch_size x num_batches) is one sample. With

    diff = inserts x samples_per_insert - samples
    offset = samples_per_insert x min_size_to_sample

a store of n is allowed while (inserts + n) x samples_per_insert - samples <= offset + error_buffer,
and a sample of k while the memory holds at least min_size_to_sample identities and
diff - k >= offset - error_buffer. Stores are free while the memory holds fewer than
min_size_to_sample identities (there is nothing to sample yet, so nothing could release them).

A store marked *relabel* (transitions a learner stored once already, sent again with fresh value
labels: ``restore_batch``) is neither checked nor counted as an insert: it is not a new
environment step, and counting it would let the sampler run ahead of the actors by the re-stores.
It is counted apart (``rate_relabelled``).

A call the limiter holds back raises :class:`RateLimited` before anything changes; the memory node
answers it with ``rate_limited: true`` and the client retries until the call passes or its timeout
runs out. So the waiting happens in the caller, never in the server: the node serves every other
client meanwhile, and the call that would release the waiting one always gets through (no
deadlock). A call that could never pass (a store of n with n x samples_per_insert larger than
the whole window 2 x error_buffer, or a sample of more than 2 x error_buffer rows) is refused as bad
input (:class:`~comper_memory.core.results.MemoryInputError`) instead of waiting for ever.

The counts are not persisted: a memory recovered from its storage starts at the balance point
(diff = offset), as if its identities had been inserted and sampled at the target ratio.
"""
from __future__ import annotations

from .results import MemoryInputError

__all__ = ["RateLimiter", "RateLimited"]


class RateLimited(RuntimeError):
    """This store or sample would break the rate limit now; nothing was changed. The same call
    may pass later, once other clients have sampled (a store) or stored (a sample)."""


class RateLimiter:
    """Samples-per-insert limiter (module text). samples_per_insert 0: no ratio (only the minimum
    size to sample applies); min_size_to_sample 0: sampling needs only what the draw itself needs."""

    #: the stats it adds to the memory's: counts of this process's life, not part of the memory's state
    STATS = ("rate_inserts", "rate_samples", "samples_per_insert_held", "rate_limited_stores",
             "rate_limited_samples", "rate_relabelled")

    def __init__(self, min_size_to_sample: int = 0, samples_per_insert: float = 0.0,
                 error_buffer: float = 0.0):
        if min_size_to_sample < 0 or samples_per_insert < 0 or error_buffer < 0:
            raise ValueError("rate limiter: min_size_to_sample, samples_per_insert and error_buffer must be >= 0")
        if samples_per_insert > 0 and error_buffer < max(1.0, samples_per_insert):
            raise ValueError(f"rate limiter: error_buffer ({error_buffer:g}) must be at least "
                             f"max(1, samples_per_insert) = {max(1.0, samples_per_insert):g}, or no "
                             "single insert could ever pass")
        self.min_size_to_sample = int(min_size_to_sample)
        self.samples_per_insert = float(samples_per_insert)
        self.error_buffer = float(error_buffer)
        self.inserts = 0
        self.samples = 0
        self.relabelled = 0          # transitions stored as relabels: neither checked nor counted as inserts
        self.blocked_inserts = 0     # store calls held back (each retry counts)
        self.blocked_samples = 0     # sample calls held back
        self._base = 0.0             # diff at the start (recovered memories start at the offset)

    @property
    def enabled(self) -> bool:
        return self.samples_per_insert > 0 or self.min_size_to_sample > 0

    @property
    def offset(self) -> float:
        return self.samples_per_insert * self.min_size_to_sample

    @property
    def diff(self) -> float:
        return self._base + self.inserts * self.samples_per_insert - self.samples

    def check_insert(self, n: int, size: int) -> None:
        """Raise RateLimited (or MemoryInputError: never) unless a store of n may go now; size = the
        memory's live identities before the store."""
        spi = self.samples_per_insert
        if spi <= 0 or size < self.min_size_to_sample:
            return
        if n * spi > 2 * self.error_buffer:
            raise MemoryInputError(
                f"store: {n} transitions x samples_per_insert {spi:g} exceed the rate limiter's whole window "
                f"(2 x error_buffer = {2 * self.error_buffer:g}): this store could never pass; send smaller "
                "batches or raise rate_error_buffer")
        after = self.diff + n * spi
        if after > self.offset + self.error_buffer:
            self.blocked_inserts += 1
            raise RateLimited(
                f"store of {n} waits for samples: it would put the samples owed at {after:g} "
                f"(inserts x {spi:g} - samples), above the limit {self.offset + self.error_buffer:g}")

    def check_sample(self, k: int, size: int) -> None:
        """Raise RateLimited (or MemoryInputError: never) unless a sample of k rows may go now."""
        if size < self.min_size_to_sample:
            self.blocked_samples += 1
            raise RateLimited(f"sample waits for stores: the memory holds {size} identities, "
                              f"min_size_to_sample is {self.min_size_to_sample}")
        spi = self.samples_per_insert
        if spi <= 0:
            return
        if k > 2 * self.error_buffer:
            raise MemoryInputError(
                f"sample: {k} rows exceed the rate limiter's whole window (2 x error_buffer = "
                f"{2 * self.error_buffer:g}): this sample could never pass; draw fewer rows per call or raise "
                "rate_error_buffer")
        after = self.diff - k
        if after < self.offset - self.error_buffer:
            self.blocked_samples += 1
            raise RateLimited(
                f"sample of {k} waits for stores: it would put the samples owed at {after:g} "
                f"(inserts x {spi:g} - samples), below the limit {self.offset - self.error_buffer:g}")

    def inserted(self, n: int, relabel: bool = False) -> None:
        if relabel:
            self.relabelled += int(n)
        else:
            self.inserts += int(n)

    def sampled(self, k: int) -> None:
        self.samples += int(k)

    def recovered(self, size: int) -> None:
        """Counts restart after a recovery: at the balance point once the memory can be sampled."""
        self.inserts = self.samples = self.relabelled = 0
        self._base = self.offset if size >= self.min_size_to_sample else 0.0

    def stats(self) -> dict:
        return {"rate_inserts": self.inserts, "rate_samples": self.samples,
                "samples_per_insert_held": self.samples / self.inserts if self.inserts else 0.0,
                "rate_limited_stores": self.blocked_inserts, "rate_limited_samples": self.blocked_samples,
                "rate_relabelled": self.relabelled}
