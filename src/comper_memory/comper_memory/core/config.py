"""MemoryConfig: every default of the compact memory, documented once (no ROS imports)."""
from __future__ import annotations

from dataclasses import dataclass

from comper_msgs_py.params import ConfigError, param

from .frames import AUTO_MIN_FRAME_BYTES, FRAME_STORE_MODES
from .key_norm import KEY_NORM_MODES

__all__ = ["MemoryConfig"]


@dataclass(frozen=True)
class MemoryConfig:
    delta: float = param(
        1e-4, "similarity threshold on the squared L2 distance between transition keys; two "
        "transitions are similar when distance <= delta, checked exactly in float64",
        thesis="1e-4 (section 5.3.2; 1e-5 and 1e-3 also studied); Table 34 lists 0.0", minimum=0.0)
    rtm_capacity: int = param(
        1_000_000, "the memory's budget: most live identities (RTM entries plus not-yet-reduced sets); above it "
        "identities chosen by `removal` are evicted from RTM, TM and the index",
        thesis="not given (RTM grows with the number of identities)", minimum=1)
    removal: str = param(
        "lru", "which identities leave when the live identities exceed rtm_capacity: lru = the least recently "
        "updated (stored or re-stored); fifo = the oldest created (with delta 0 every transition is its own "
        "identity, so this is a FIFO replay buffer of rtm_capacity transitions); reservoir = a uniform sample of "
        "every identity ever created (Vitter's algorithm R over identities: the j-th new identity is kept with "
        "probability rtm_capacity / j, in place of a uniformly chosen one), drawn from removal_seed and the "
        "identity's id, so a WAL replay evicts the same ones; coverage = where the keys are densest (of 4 "
        "uniformly drawn candidates per identity to evict, at least 64, the one nearest to a uniform sample of up "
        "to 2,048 live identities, fewer for long keys, leaves, in turn; de Bruin et al., JMLR 2018), drawn from "
        "removal_seed and the store's first new id",
        thesis="not given (the thesis never fills RTM)", choices=("lru", "fifo", "reservoir", "coverage"))
    removal_seed: int = param(0, "seed of the reservoir and coverage removal draws", minimum=0)
    delta_rule: str = param(
        "fixed", "fixed = delta as given; nn_quantile = delta follows the keys' spread: at each key normaliser freeze "
        "(key_norm_growth; the first once 256 identities live) keys are scaled so that delta sits at the "
        "delta_quantile quantile of squared nearest-neighbour distances between up to 1,024 live identities and up "
        "to 4,096 (fewer for long keys), evenly spread over the ids (docs/memory.md, 'Key normalisation')",
        thesis="fixed (section 5.3.2)", deviation="nn_quantile is not in the thesis: at a fixed delta MuJoCo keys "
        "form no sets", choices=("fixed", "nn_quantile"))
    delta_quantile: float = param(
        0.1, "delta_rule nn_quantile: the quantile of nearest-neighbour distances delta is set to (higher: "
        "more transitions join a set, coarser sets; docs/memory.md, 'Key normalisation', has identities per "
        "1,000 transitions at 0.05-0.5)", minimum=0.0, maximum=1.0)
    tm_capacity: int = param(
        100_000, "maximum number of similar-transition sets waiting in TM; above it the least "
        "recently updated identity among them is evicted from TM, RTM and the index",
        thesis="100,000 sets (Table 34, 'Transition memory size')", minimum=1)
    history_length: int = param(
        32, "value labels kept per similar-transition set (time-ordered, newest kept)",
        thesis="unbounded in the text (eq. 4.2); bounded here so memory per identity is fixed",
        minimum=1)
    reduce_batch: int = param(
        1000, "sets popped from TM (oldest first) per reduction",
        thesis="1,000 for COMPER (Table 34, 'Similar transitions batch size'); 50,000 for COMCACT (App. B)",
        minimum=1)
    max_store_batch: int = param(
        16384, "largest number of transitions accepted by one store call (larger calls are refused)",
        minimum=1)
    max_sample_batch: int = param(
        65536, "largest number of entries returned by one sample call", minimum=1)
    min_size_to_sample: int = param(
        0, "rate limiter: sample calls wait until the memory holds this many live identities (0 = no minimum)",
        thesis="none (the learner samples from the first step)", minimum=0)
    samples_per_insert: float = param(
        0.0, "rate limiter: rows sampled per transition stored that the memory holds all clients to, within "
        "rate_error_buffer (a store or sample that would leave the band waits in its client); 0 = no ratio. "
        "Reverb's SampleToInsertRatio (docs/memory-service.md)", thesis="none (lock step, Algorithm 7 / 8)",
        minimum=0.0)
    rate_error_buffer: float = param(
        0.0, "rate limiter: how far (in samples) the balance inserts x samples_per_insert - samples may drift "
        "either side of samples_per_insert x min_size_to_sample; at least max(1, samples_per_insert) when a "
        "ratio is set, and a store of n needs n x samples_per_insert <= 2 x this", minimum=0.0)
    frame_scale: float = param(
        1.0 / 255.0, "factor applied once to uint8 observations when building keys (float32 "
        "observations are used raw)", thesis="frames scaled to [0, 1] (section 5.1)", minimum=0.0)
    frame_store: str = param(
        "auto", "how representatives keep their observations: 'on' = by reference, each distinct frame stored once "
        "(found by its bytes) and a state or next state kept as the ids of its frames, rebuilt byte for byte when "
        "read (keys, samples, snapshots); 'off' = whole observations per identity; 'auto' = 'on' for uint8 "
        f"observations stacked along frame_axis (3 or more dimensions) whose frames hold at least "
        f"{AUTO_MIN_FRAME_BYTES} bytes (stacked Atari frames), else 'off'. Decisions and samples are identical "
        "either way (docs/memory.md, 'Frame store')", choices=FRAME_STORE_MODES)
    frame_axis: int = param(
        0, "frame_store: the observation axis frames are stacked along (0: [stack, H, W], the suite's Atari "
        "observations; 2 for [H, W, stack]); -1 = the whole observation is one frame (camera images), as is any "
        "observation of fewer than 3 dimensions", minimum=-1)
    key_normalisation: str = param(
        "none", "how keys are scaled before every similarity decision: 'none' (raw [s, a, r, s']) or 'running' "
        "(each dimension standardised by the running mean and standard deviation of the keys stored so far, "
        "frozen between reductions; the memory re-indexes when they change; delta is then in standard "
        "deviations; docs/memory.md, 'Key normalisation')", thesis="raw keys (section 4.2)",
        deviation="'running' is not in the thesis: with raw MuJoCo keys at delta 1e-4 no two transitions are "
        "similar", choices=KEY_NORM_MODES)
    key_norm_growth: float = param(
        2.0, "key_normalisation running: replace the frozen mean and scale at a reduction once the keys stored "
        "have grown this many times since the last replacement (so re-indexing happens about log2(n) times)",
        minimum=1.01)
    key_norm_min_std: float = param(
        1e-6, "key_normalisation running: a key dimension whose standard deviation is below this keeps scale 1",
        minimum=0.0)
    storage_dir: str = param(
        "", "directory for the write-ahead log and snapshots; '' keeps the memory in process only")
    durability: str = param(
        "flush", "when a store is acknowledged: 'flush' (WAL written to the OS, survives a killed "
        "process), 'fsync' (also on disk, survives power loss), 'none' (buffered, may lose the tail)",
        choices=("flush", "fsync", "none"))
    wal_accept_loss: bool = param(
        False, "start even when the write-ahead log is damaged or ends before the sequence its mark "
        "(storage_dir/wal.mark, written at start, checkpoint and clean stop) records: replay keeps every "
        "intact record, before and after the damage (a record whose header alone is damaged is kept too), "
        "drops the damaged bytes and logs what was dropped (byte ranges, sequences); each damaged file is "
        "first copied to <file>.damaged-<offset>. false: start-up stops with the file, offsets, records "
        "after the damage or the missing sequences, and nothing is changed. A torn last record (the "
        "process was killed while writing it, so it was never acknowledged) is always dropped, with a "
        "warning and a copy in <file>.torn-<offset>. Set it for the one start that accepts the loss")
    max_key_abs: float = param(
        1e8, "largest magnitude of any key value (observation, action, reward; uint8 frames after "
        "frame_scale); a store holding a larger value is refused whole with the transition and key "
        "position named. Any bound up to 3e38 keeps stores fast: keys too large for the grid index's "
        "cells (float64 rounding, docs/memory.md, 'Limits') are indexed apart by their norm and slow "
        "only stores of keys of about the same norm. Leaves room for step counters in observations "
        "(1e8 steps)",
        deviation="not in the thesis (inputs are unbounded there)", minimum=0.0, maximum=3e38)
    resend_window: int = param(
        1_000_000, "transitions of store answers the memory remembers by the client's request id (oldest "
        "forgotten first; 8 bytes each): a store re-sent with the id of a remembered one is answered with that "
        "answer and not applied again. 0 = none remembered (every store is applied). With storage_dir the answers "
        "survive a restart (WAL and snapshots), and a batch a kill cut short between chunks is completed by its "
        "re-send (waited for until resend_window transitions of newer answers are remembered, then forgotten)",
        deviation="not in the thesis (one process there)", minimum=0)
    snapshot_every: int = param(
        10_000, "write a snapshot and rotate the WAL every this many logged operations (0: never)",
        minimum=0)
    lease_timeout_s: float = param(
        300.0, "seconds a two-phase reduction lease stays valid; expired leases put their sets back "
        "at the front of TM. It only needs to run out when the QT trainer died mid-round, so it is sized "
        "above the longest round seen: 4,000 sets of 4-frame Atari keys (COMPER, data_efficient) took over "
        "60 s on a loaded 2-core machine", minimum=0.0)
    index_engine: str = param(
        "grid", "exact candidate generator of the similarity index: 'grid' (sorted cell codes over a "
        "3-d PCA projection, numpy) or 'faiss_ivf' (faiss IVF over an orthonormal projection with the "
        "triangle-inequality probe bound); both re-check every candidate in float64, so decisions are "
        "identical and only speed differs (docs/memory.md has the measured comparison)",
        thesis="faiss IndexFlatL2 brute force (Appendix A.1)",
        deviation="grid is the default for speed (docs/memory.md); faiss_ivf keeps faiss as the search engine",
        choices=("grid", "faiss_ivf"))
    index_projection_dim: int = param(
        8, "dimensions of the orthonormal projection the exact index partitions on "
        "(|P(x - y)| <= |x - y|, so no similar pair is missed; larger = fewer exact re-checks, "
        "more memory); the grid engine (default) partitions on min(3, this) PCA directions and "
        "filters candidates on min(this, 64), the faiss IVF engine uses this many", minimum=1, maximum=256)
    index_min_train: int = param(
        2048, "identities before the index fits its partition to the data (grid: PCA directions and "
        "extent; IVF: k-means lists, one list below)",
        minimum=16)
    index_list_size: int = param(
        64, "target identities per index list (nlist = identities / this, capped; IVF engine only)", minimum=8)
    index_max_lists: int = param(
        4096, "largest number of index lists (IVF engine only)", minimum=1)
    index_rebuild_growth: float = param(
        4.0, "rebuild (re-train) the index partition when identities grow by this factor",
        minimum=1.5)
    index_seed: int = param(0, "seed of the projection and k-means (affects speed only, never results)")

    def validate(self) -> "MemoryConfig":
        if self.max_store_batch > self.rtm_capacity:
            raise ConfigError(f"max_store_batch ({self.max_store_batch}) must not exceed "
                              f"rtm_capacity ({self.rtm_capacity})")
        if self.max_store_batch > self.tm_capacity:
            raise ConfigError(f"max_store_batch ({self.max_store_batch}) must not exceed "
                              f"tm_capacity ({self.tm_capacity})")
        if self.samples_per_insert > 0 and self.rate_error_buffer < max(1.0, self.samples_per_insert):
            raise ConfigError(f"rate_error_buffer ({self.rate_error_buffer:g}) must be at least "
                              f"max(1, samples_per_insert) = {max(1.0, self.samples_per_insert):g} when "
                              "samples_per_insert is set")
        if self.key_normalisation not in KEY_NORM_MODES:
            raise ConfigError(f"key_normalisation {self.key_normalisation!r} is not one of {', '.join(KEY_NORM_MODES)}")
        if self.delta_rule == "nn_quantile" and not (self.delta > 0 and 0 < self.delta_quantile < 1):
            raise ConfigError(f"delta_rule nn_quantile needs delta > 0 and 0 < delta_quantile < 1 (got delta "
                              f"{self.delta:g}, delta_quantile {self.delta_quantile:g})")
        if self.frame_store not in FRAME_STORE_MODES:
            raise ConfigError(f"frame_store {self.frame_store!r} is not one of {', '.join(FRAME_STORE_MODES)}")
        if self.durability not in ("flush", "fsync", "none"):
            raise ConfigError(f"durability {self.durability!r} is not one of flush, fsync, none")
        return self
