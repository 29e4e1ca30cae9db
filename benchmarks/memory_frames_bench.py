#!/usr/bin/env python3
"""Memory per transition of stacked Atari observations: whole stacks per identity (before), the frame store
(after, ``frame_store`` auto) and a Dopamine-style anchor, measured in one run (issue 59, item 4).

1. Plays ``--record`` steps (default: the largest size) with the suite's own ALE pipeline (comper_sim SimBridge,
   method.md section 5 protocol, uniformly random actions) and records the stream once to ``--workdir``: each frame
   once in order of play (an episode's first frame, then one per step) and per transition its frame's position
   and its episode's first position. Sizes above ``--record`` replay the recording again, each pass's frames
   marked with the pass number in their top-left 8 pixels (0 or 255 each), so no frame of one pass equals one of
   another (every pass is new to each variant, none is found again by the frame store); the recording's last
   transition counts as truncated, so a pass starts a new episode.
2. For each size and variant, one fresh process reads the stream in batches of ``--batch`` and builds the
   [4, 84, 84] stacks the sim builds (oldest first, an episode's first stack filled with its first frame), then:
   * ``before``: CompactMemory with ``frame_store`` off (each identity holds s and s' whole, today's layout);
   * ``after``: CompactMemory with ``frame_store`` auto (each frame once, stacks as frame ids);
   * ``anchor``: a plain uint8 ring of frames with stacking by index (one frame per step plus an episode's first
     frame; a transition keeps the ring position of its state's newest frame and its episode's first; stacks
     gathered by index, clamped at the episode start), as Dopamine's circular replay keeps Atari;
   and measures: RSS after the stores minus RSS before (bytes per transition), the memory's own count
   (``bytes_used``), peak RSS, store throughput (time inside store calls), sample throughput (``--sample-calls``
   draws of 64 from TM; the anchor: 64 uniform indices), snapshot size and time (``save_snapshot``; the anchor:
   ``np.savez`` of its arrays). rtm_capacity and tm_capacity are the size (nothing is evicted), delta 1e-4.
3. Prints one table with ratios against the anchor and against ``before`` of the same size; a size above
   ``--before-max`` gets ``before`` extrapolated linearly from its largest measured size (marked as such: at
   1,000,000 transitions it needs ~57 GB, more than the machine).

    python benchmarks/memory_frames_bench.py --sizes 100000 1000000 --before-max 100000
    python benchmarks/memory_frames_bench.py --sizes 20000 --workdir fb-work     # a quick look
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

STACK = 4
FRAME = (84, 84)
FRAME_BYTES = FRAME[0] * FRAME[1]


# ---------------------------------------------------------------- the stream
def record(game: str, n: int, seed: int, workdir: str) -> None:
    """Play n steps, write frames.u8 (each frame once, in order) and stream.npz (per transition)."""
    from comper_sim.core import SimBridge, SimConfig
    b = SimBridge(SimConfig(env_id=game))
    b.reset(seed=seed)
    rng = np.random.default_rng(seed)
    pos, start = np.zeros(n, np.int64), np.zeros(n, np.int64)
    act, rew = np.zeros(n, np.int64), np.zeros(n, np.float32)
    term, trunc = np.zeros(n, bool), np.zeros(n, bool)
    written, ep_start, ended, done = 0, 0, True, 0
    with open(os.path.join(workdir, "frames.u8"), "wb") as f:
        while done < n:
            k = min(1000, n - done)
            t = b.step_many(rng.integers(0, 18, k).astype(np.float32)).transitions
            for i in range(len(t)):
                if ended:                                  # an episode's first frame
                    f.write(t.states[i].tobytes())
                    ep_start = written
                    written += 1
                j = done + i
                pos[j], start[j] = written - 1, ep_start
                f.write(t.next_states[i].tobytes())
                written += 1
                act[j], rew[j], term[j], trunc[j] = t.actions[i], t.rewards[i], t.terminated[i], t.truncated[i]
                ended = bool(t.terminated[i] or t.truncated[i])
            done += len(t)
    b.close()
    np.savez(os.path.join(workdir, "stream.npz"), pos=pos, start=start, actions=act, rewards=rew,
             terminated=term, truncated=trunc, frames=np.int64(written))


class Stream:
    """Reads the recorded stream back in order as stacked Transitions (file reads, nothing mapped: RSS stays the
    measured memory's)."""

    def __init__(self, workdir: str):
        z = np.load(os.path.join(workdir, "stream.npz"))
        self.a = {k: z[k] for k in z.files}
        self.a["truncated"][-1] = True
        self.n = len(self.a["pos"])
        self.f = open(os.path.join(workdir, "frames.u8"), "rb")

    def batch(self, lo: int, hi: int):
        from comper_msgs_py.arrays import Transitions
        p, j = divmod(lo, self.n)
        if j + hi - lo > self.n:                            # across the end of a pass
            return Transitions.concatenate([self.batch(lo, lo + self.n - j), self.batch(lo + self.n - j, hi)])
        t = self._batch(j, j + hi - lo)
        if p:
            mark = np.where((p >> np.arange(8)) & 1, 255, 0).astype(np.uint8)
            t.states[..., 0, :8] = mark
            t.next_states[..., 0, :8] = mark
        return Transitions(t.states, t.actions, t.rewards, t.next_states, t.terminated, t.truncated,
                           value_labels=t.value_labels, episode_ids=t.episode_ids,
                           steps=np.arange(lo, hi, dtype=np.uint64))

    def _batch(self, lo: int, hi: int):
        from comper_msgs_py.arrays import Transitions
        a = self.a
        pos, start = a["pos"][lo:hi], a["start"][lo:hi]
        first, last = int(np.maximum(start, pos - STACK + 1).min()), int(pos.max()) + 1
        self.f.seek(first * FRAME_BYTES)
        frames = np.frombuffer(self.f.read((last + 1 - first) * FRAME_BYTES), np.uint8).reshape(-1, *FRAME)
        back = np.arange(-STACK + 1, 1)
        s = np.maximum(pos[:, None] + back, start[:, None]) - first
        s2 = np.maximum(pos[:, None] + 1 + back, start[:, None]) - first
        n = hi - lo
        return Transitions(frames[s], a["actions"][lo:hi], a["rewards"][lo:hi], frames[s2],
                           a["terminated"][lo:hi], a["truncated"][lo:hi], value_labels=np.zeros(n, np.float32),
                           episode_ids=np.zeros(n, np.uint64), steps=np.arange(lo, hi, dtype=np.uint64))


# ---------------------------------------------------------------- the anchor
class FrameRing:
    """Dopamine-style storage: one ring of uint8 frames (an episode's first frame, then one per step), and per
    transition the ring position of its state's newest frame and of its episode's first; a stack is gathered by
    index, positions before the episode's first clamped to it (the sim's fill)."""

    def __init__(self, capacity: int, margin: int = 4096):
        self.cap = capacity
        self.n_frames = capacity + margin
        self.frames = np.zeros((self.n_frames, *FRAME), np.uint8)
        self.newest = np.zeros(capacity, np.int64)
        self.first = np.zeros(capacity, np.int64)
        self.actions = np.zeros(capacity, np.int32)
        self.rewards = np.zeros(capacity, np.float32)
        self.terminated = np.zeros(capacity, bool)
        self.truncated = np.zeros(capacity, bool)
        self.size = self.written = 0
        self.ep_first, self.ended = 0, True

    def _put(self, frame: np.ndarray) -> int:
        self.frames[self.written % self.n_frames] = frame
        self.written += 1
        return self.written - 1

    def add(self, t) -> None:
        for i in range(len(t)):
            if self.ended:
                self.ep_first = self._put(t.states[i][-1])
            j = self.size % self.cap
            self.newest[j], self.first[j] = self.written - 1, self.ep_first
            self._put(t.next_states[i][-1])
            self.actions[j], self.rewards[j] = t.actions[i], t.rewards[i]
            self.terminated[j], self.truncated[j] = t.terminated[i], t.truncated[i]
            self.ended = bool(t.terminated[i] or t.truncated[i])
            self.size += 1

    def take(self, idx: np.ndarray):
        from comper_msgs_py.arrays import Transitions
        back = np.arange(-STACK + 1, 1)
        p, e = self.newest[idx][:, None], self.first[idx][:, None]
        s = self.frames[np.maximum(p + back, e) % self.n_frames]
        s2 = self.frames[np.maximum(p + 1 + back, e) % self.n_frames]
        return Transitions(s, self.actions[idx], self.rewards[idx], s2, self.terminated[idx], self.truncated[idx])

    def arrays(self) -> dict:
        n = min(self.size, self.cap)
        return {"frames": self.frames[:min(self.written, self.n_frames)], "newest": self.newest[:n],
                "first": self.first[:n], "actions": self.actions[:n], "rewards": self.rewards[:n],
                "terminated": self.terminated[:n], "truncated": self.truncated[:n]}

    def bytes_used(self) -> int:
        return int(min(self.written, self.n_frames) * FRAME_BYTES + self.cap * (8 + 8 + 4 + 4 + 1 + 1))


# ---------------------------------------------------------------- one variant, in its own process
def proc_status() -> dict:
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "VmHWM", "RssAnon"):
                out[k] = int(v.split()[0]) * 1024
    return out


def dir_bytes(path: str) -> int:
    if os.path.isfile(path):
        return os.path.getsize(path)
    return sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(path) for f in fs)


def run_variant(variant: str, n: int, args) -> dict:
    from comper_memory.core import CompactMemory, MemoryConfig
    stream = Stream(args.workdir)
    if variant == "anchor":
        mem = FrameRing(n)
    else:
        mem = CompactMemory(MemoryConfig(frame_store="off" if variant == "before" else "auto", rtm_capacity=n,
                                         tm_capacity=n, max_store_batch=args.batch))
    base = proc_status()
    spent = 0.0
    for lo in range(0, n, args.batch):
        t = stream.batch(lo, min(n, lo + args.batch))
        t0 = time.perf_counter()
        mem.add(t) if variant == "anchor" else mem.store(t)
        spent += time.perf_counter() - t0
        if lo % 100_000 == 0 and lo:
            print(f"[bench] {variant} {n}: {lo} stored, {lo / spent:.0f} tr/s, RSS {proc_status()['VmRSS'] / 1e9:.2f} GB",
                  file=sys.stderr, flush=True)
    filled = proc_status()
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for i in range(args.sample_calls):
        if variant == "anchor":
            mem.take(rng.integers(0, min(mem.size, mem.cap), 64))
        else:
            mem.sample(64, source="tm", seed=i)
    sample_s = time.perf_counter() - t0
    if variant == "anchor":   # the anchor gives back the stacks it was given
        idx = rng.integers(0, n, 16)
        ref = [stream.batch(int(i), int(i) + 1) for i in idx]
        got = mem.take(idx)
        assert all(np.array_equal(got.states[k], r.states[0]) and np.array_equal(got.next_states[k], r.next_states[0])
                   for k, r in enumerate(ref))
    snap = os.path.join(args.workdir, f"snap-{variant}-{n}")
    t0 = time.perf_counter()
    if variant == "anchor":
        snap += ".npz"
        np.savez(snap, **mem.arrays())
    else:
        mem.save_snapshot(snap)
    snap_s = time.perf_counter() - t0
    snap_bytes = dir_bytes(snap)
    shutil.rmtree(snap, ignore_errors=True) if os.path.isdir(snap) else os.remove(snap)
    after = proc_status()
    stats = {} if variant == "anchor" else mem.stats()
    return {"variant": variant, "n": n, "rss_base": base["VmRSS"], "rss": filled["VmRSS"],
            "anon": filled["RssAnon"] - base["RssAnon"], "peak_fill": filled["VmHWM"], "peak_snapshot": after["VmHWM"],
            "own_bytes": mem.bytes_used(), "store_s": spent, "sample_s": sample_s, "sample_rows": 64 * args.sample_calls,
            "snapshot_bytes": snap_bytes, "snapshot_s": snap_s, "identities": stats.get("identities", n)}


# ---------------------------------------------------------------- the report
def report(rows: list[dict]) -> None:
    by = {(r["variant"], r["n"]): r for r in rows}
    measured_before = sorted(n for v, n in by if v == "before")

    def per_tr(r):
        return (r["rss"] - r["rss_base"]) / r["n"]

    print("\n| transitions | variant | bytes/transition (RSS) | own count | RSS GB | peak RSS GB (fill / snapshot) | "
          "snapshot GB | store tr/s | sample rows/s | identities |")
    print("|---" * 10 + "|")
    for n in sorted({r["n"] for r in rows}):
        for v in ("anchor", "before", "after"):
            r = by.get((v, n))
            if r is None and v == "before" and measured_before:
                m = by[("before", measured_before[-1])]
                print(f"| {n:,} | before (extrapolated from {m['n']:,}) | {per_tr(m):,.0f} | "
                      f"{m['own_bytes'] / m['n']:,.0f} | {per_tr(m) * n / 1e9:.1f} | - | "
                      f"{m['snapshot_bytes'] / m['n'] * n / 1e9:.1f} | - | - | - |")
                continue
            if r is None:
                continue
            print(f"| {n:,} | {v} | {per_tr(r):,.0f} | {r['own_bytes'] / n:,.0f} | {r['rss'] / 1e9:.2f} | "
                  f"{r['peak_fill'] / 1e9:.2f} / {r['peak_snapshot'] / 1e9:.2f} | {r['snapshot_bytes'] / 1e9:.2f} | "
                  f"{n / r['store_s']:,.0f} | {r['sample_rows'] / r['sample_s']:,.0f} | {r['identities']:,} |")
    print()
    for n in sorted({r["n"] for r in rows}):
        a, aft, bef = by.get(("anchor", n)), by.get(("after", n)), by.get(("before", n))
        if a and aft:
            print(f"[bench] {n:,}: after / anchor bytes per transition {per_tr(aft) / per_tr(a):.3f} (own count "
                  f"{aft['own_bytes'] / a['own_bytes']:.3f}), snapshot {aft['snapshot_bytes'] / a['snapshot_bytes']:.3f}")
        if bef and aft:
            print(f"[bench] {n:,}: after / before bytes per transition {per_tr(aft) / per_tr(bef):.3f}, snapshot "
                  f"{aft['snapshot_bytes'] / bef['snapshot_bytes']:.3f}, store throughput "
                  f"{bef['store_s'] / aft['store_s']:.2f}x, sample throughput {bef['sample_s'] / aft['sample_s']:.2f}x")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--game", default="ALE/Seaquest-v5")
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000], help="transitions stored")
    ap.add_argument("--before-max", type=int, default=100_000, help="largest size 'before' is measured at")
    ap.add_argument("--record", type=int, default=0, help="ALE steps played (0: the largest size; larger sizes "
                    "replay them, marked per pass)")
    ap.add_argument("--variants", nargs="+", default=["anchor", "before", "after"])
    ap.add_argument("--batch", type=int, default=64, help="transitions per store call")
    ap.add_argument("--sample-calls", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", default=os.path.join(tempfile.gettempdir(), "memory_frames_bench"),
                    help="the recorded stream and snapshots (default: memory_frames_bench in the temporary folder)")
    ap.add_argument("--out", default="", help="write the rows as JSON here")
    ap.add_argument("--run-variant", default="", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.run_variant:
        print(json.dumps(run_variant(args.run_variant, args.n, args)), flush=True)
        return
    os.makedirs(args.workdir, exist_ok=True)
    need = args.record or max(args.sizes)
    have = os.path.join(args.workdir, "stream.npz")
    if not os.path.exists(have) or len(np.load(have)["pos"]) < need:
        t0 = time.perf_counter()
        record(args.game, need, args.seed, args.workdir)
        print(f"[bench] {need:,} {args.game} steps played and recorded in {time.perf_counter() - t0:.0f} s", flush=True)
    rows = []
    for n in sorted(args.sizes):
        for v in args.variants:
            if v == "before" and n > args.before_max:
                continue
            cmd = [sys.executable, __file__, "--run-variant", v, "--n", str(n), "--workdir", args.workdir,
                   "--batch", str(args.batch), "--sample-calls", str(args.sample_calls)]
            t0 = time.perf_counter()
            out = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
            print(f"[bench] {v} at {n:,}: {time.perf_counter() - t0:.0f} s", flush=True)
            if args.out:
                with open(args.out, "w") as f:
                    json.dump(rows, f, indent=1)
    report(rows)


if __name__ == "__main__":
    main()
