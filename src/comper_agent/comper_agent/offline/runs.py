"""Offline evaluation from recorded bags (pure: rosbags + numpy; torch only for --checkpoint).

* :func:`read_runs` reads bags (types registered ONLY from the bags themselves) into one
  :class:`RunData` per training run: the EpisodeSummary messages (train / eval / sim), the
  EvaluationResult messages, the MemoryStats gauge and all recorded transitions (numpy).
* :func:`reconstruct_episodes` cuts transitions into episodes (by episode_ids, else by the
  terminated / truncated flags) and sums their rewards (the cross-check of the published returns).
* :func:`final_performance`, :func:`tercile_summaries`, :func:`run_summary`, :func:`group_summaries`:
  the thesis's summaries (method.md section 5).
* :func:`discounted_returns`; :func:`q_vs_mc`, :func:`fitted_q_evaluation`, :func:`load_policy`
  (in :mod:`comper_agent.offline.value_checks`): the checkpoint's value estimates against what the logged
  episodes actually returned.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from comper_msgs_py.arrays import Transitions

from comper_agent.core.protocol import final_performance, last_n_rule, tercile_summaries

__all__ = [
    "EpisodeRecord", "EvalPoint", "RunData", "Episode", "find_bags", "read_runs",
    "reconstruct_episodes", "discounted_returns", "final_performance", "last_n_rule",
    "tercile_summaries", "eval_points", "run_summary", "group_summaries", "cross_check"]

TRAIN, EVAL, SIM = "train", "eval", "sim"


# --------------------------------------------------------------------------------------------
# data
@dataclass
class EpisodeRecord:
    """One EpisodeSummary message (float64 return exactly as published)."""
    run_id: str
    env_id: str
    source: str
    episode_id: int
    episode_return: float
    length: int
    frames: int
    terminated: bool
    truncated: bool
    global_step: int
    global_frames: int
    wall_time_s: float
    topic: str = ""


@dataclass
class EvalPoint:
    """One EvaluationResult message."""
    run_id: str
    algorithm: str
    env_id: str
    global_step: int
    episode_returns: list
    episode_lengths: list
    mean_return: float
    std_return: float


@dataclass
class RunData:
    run_id: str
    bags: list = field(default_factory=list)
    env_id: str = ""
    algorithm: str = ""
    episodes: list = field(default_factory=list)        # EpisodeRecord, all sources
    evaluations: list = field(default_factory=list)     # EvalPoint
    stats: list = field(default_factory=list)           # MemoryStats as dicts
    transitions: Transitions | None = None
    warnings: list = field(default_factory=list)

    def train_episodes(self) -> list:
        return sorted((e for e in self.episodes if e.source == TRAIN), key=lambda e: (e.episode_id, e.global_step))

    def eval_episodes(self) -> list:
        return [e for e in self.episodes if e.source == EVAL]


def find_bags(paths) -> list[Path]:
    """Bag directories (holding metadata.yaml) given bags or run directories (searched recursively)."""
    out, seen = [], set()
    for p in map(Path, paths):
        if not p.exists():
            raise FileNotFoundError(f"{p} does not exist")
        cands = [p] if (p / "metadata.yaml").is_file() else sorted(m.parent for m in p.rglob("metadata.yaml"))
        for c in cands:
            if ".open" in c.parts:
                continue
            r = c.resolve()
            if r not in seen:
                seen.add(r)
                out.append(c)
    if not out:
        raise FileNotFoundError(f"no rosbag2 bag (metadata.yaml) under {', '.join(map(str, paths))}")
    return out


def _np(seq, dtype) -> np.ndarray:
    return np.asarray(seq, dtype=dtype).reshape(-1)


def _array(msg) -> np.ndarray:
    shape = tuple(int(d) for d in msg.shape)
    data = _np(msg.data_u8, np.uint8) if msg.dtype == 1 else _np(msg.data_f32, np.float32)
    return data.reshape(shape)


def _transitions(msg) -> Transitions:
    return Transitions(
        states=_array(msg.states), actions=_array(msg.actions), rewards=_np(msg.rewards, np.float32),
        next_states=_array(msg.next_states), terminated=_np(msg.terminated, bool),
        truncated=_np(msg.truncated, bool), value_labels=_np(msg.value_labels, np.float32),
        episode_ids=_np(msg.episode_ids, np.uint64), steps=_np(msg.steps, np.uint64), run_id=msg.run_id)


def read_runs(paths, *, load_transitions: bool = True) -> dict[str, RunData]:
    """Read every bag under `paths` into RunData per run_id (bags of one run are merged).

    The typestore is built only from the definitions embedded in each bag.
    """
    from rosbags.rosbag2 import Reader

    from comper_agent.recording.bags import bag_info, bag_typestore

    runs: dict[str, RunData] = {}
    parts: dict[str, list] = {}
    for bag in find_bags(paths):
        with Reader(bag) as reader:
            store = bag_typestore(reader.connections)
            custom = bag_info(bag).get("custom_data") or {}
            default_run = custom.get("run_id") or bag.parent.name
            algo = custom.get("algorithm", "")
            touched = set()
            for conn, _ts, raw in reader.messages():
                typ = conn.msgtype.rsplit("/", 1)[-1]
                if typ not in ("EpisodeSummary", "EvaluationResult", "TransitionBatch", "MemoryStats"):
                    continue
                if typ == "TransitionBatch" and not load_transitions:
                    continue
                msg = store.deserialize_cdr(raw, conn.msgtype)
                rid = getattr(msg, "run_id", "") or default_run
                run = runs.setdefault(rid, RunData(rid))
                touched.add(rid)
                if typ == "EpisodeSummary":
                    run.episodes.append(EpisodeRecord(
                        rid, msg.env_id, msg.source, int(msg.episode_id), float(msg.episode_return),
                        int(msg.length), int(msg.frames), bool(msg.terminated), bool(msg.truncated),
                        int(msg.global_step), int(msg.global_frames), float(msg.wall_time_s), conn.topic))
                    run.env_id = run.env_id or msg.env_id
                elif typ == "EvaluationResult":
                    run.evaluations.append(EvalPoint(
                        rid, msg.algorithm, msg.env_id, int(msg.global_step),
                        _np(msg.episode_returns, np.float64).tolist(),
                        _np(msg.episode_lengths, np.int64).tolist(),
                        float(msg.mean_return), float(msg.std_return)))
                    run.algorithm = msg.algorithm or run.algorithm
                    run.env_id = run.env_id or msg.env_id
                elif typ == "TransitionBatch":
                    parts.setdefault(rid, []).append(_transitions(msg))
                else:
                    run.stats.append({k: (v.item() if hasattr(v, "item") else v)
                                      for k, v in vars(msg).items() if k not in ("header", "__msgtype__")})
            for rid in touched:
                runs[rid].bags.append(str(bag))
                if algo and not runs[rid].algorithm:
                    runs[rid].algorithm = algo
                if not runs[rid].algorithm:
                    # fall back to the publishing node's name: /comcact_node/episodes -> comcact
                    topics = [e.topic for e in runs[rid].episodes if e.source == TRAIN]
                    if topics:
                        runs[rid].algorithm = topics[0].strip("/").split("/")[0].removesuffix("_node")
    for rid, run in runs.items():
        _dedupe(run)
        if parts.get(rid):
            t = Transitions.concatenate(parts[rid])
            if t.steps.size == len(t):
                order = np.argsort(t.steps, kind="stable")
                keep = np.ones(len(t), bool)
                keep[1:] = np.diff(t.steps[order].astype(np.int64)) != 0
                if not keep.all():
                    run.warnings.append(f"{int((~keep).sum())} duplicate transitions (same step) dropped")
                t = t.take(order[keep])
            run.transitions = t
    return runs


def _dedupe(run: RunData) -> None:
    seen, eps = set(), []
    for e in run.episodes:
        k = (e.source, e.episode_id, e.global_step, e.topic if e.source == SIM else "")
        if k in seen:
            continue
        seen.add(k)
        eps.append(e)
    if len(eps) != len(run.episodes):
        run.warnings.append(f"{len(run.episodes) - len(eps)} duplicate episode summaries dropped")
    run.episodes = eps
    seen, evs = set(), []
    for ev in sorted(run.evaluations, key=lambda x: x.global_step):
        if ev.global_step not in seen:
            seen.add(ev.global_step)
            evs.append(ev)
    run.evaluations = evs


# --------------------------------------------------------------------------------------------
# episodes and returns
@dataclass
class Episode:
    episode_id: int
    index: np.ndarray      # indices into the transitions, in step order
    length: int
    episode_return: float  # float64 sum of the float32 rewards
    terminated: bool
    truncated: bool
    complete: bool         # ends with terminated or truncated
    contiguous: bool       # steps consecutive and next_state[t] == state[t+1]


def reconstruct_episodes(t: Transitions) -> list[Episode]:
    """Cut transitions into episodes: by episode_ids when filled, else at terminated|truncated."""
    n = len(t)
    if n == 0:
        return []
    if t.episode_ids.size == n:
        key = t.episode_ids.astype(np.int64)
        sub = t.steps.astype(np.int64) if t.steps.size == n else np.arange(n)
        order = np.lexsort((sub, key))
        ks = key[order]
        cuts = np.flatnonzero(np.diff(ks)) + 1
        groups = np.split(order, cuts)
        ids = [int(key[g[0]]) for g in groups]
    else:
        ends = np.flatnonzero(t.terminated | t.truncated) + 1
        groups = [g for g in np.split(np.arange(n), ends) if g.size]
        ids = list(range(len(groups)))
    out = []
    steps = t.steps.astype(np.int64) if t.steps.size == n else None
    for eid, g in zip(ids, groups):
        last = g[-1]
        term, trunc = bool(t.terminated[last]), bool(t.truncated[last])
        contiguous = True
        if g.size > 1:
            if steps is not None and not np.all(np.diff(steps[g]) == 1):
                contiguous = False
            elif not np.array_equal(t.next_states[g[:-1]], t.states[g[1:]]):
                contiguous = False
        out.append(Episode(eid, g, int(g.size), float(np.sum(t.rewards[g], dtype=np.float64)),
                           term, trunc, term or trunc, contiguous))
    return out


def discounted_returns(rewards: np.ndarray, episode_ends: np.ndarray, gamma: float) -> np.ndarray:
    """Monte-Carlo returns G_t = r_t + gamma G_{t+1}, restarted after each index where
    episode_ends is true (float64). Rewards must be in time order."""
    r = np.asarray(rewards, dtype=np.float64)
    ends = np.asarray(episode_ends, dtype=bool)
    g = np.empty_like(r)
    acc = 0.0
    for i in range(r.size - 1, -1, -1):
        if ends[i]:
            acc = 0.0
        acc = r[i] + gamma * acc
        g[i] = acc
    return g


# --------------------------------------------------------------------------------------------
# the thesis's summaries (method.md section 5)
# last_n_rule, final_performance, tercile_summaries: core/protocol.py (also used by comper_node)


def eval_points(run: RunData) -> list[dict]:
    """Evaluation points: EvaluationResult messages, else eval EpisodeSummaries grouped by step."""
    if run.evaluations:
        return [{"global_step": e.global_step, "mean": e.mean_return, "std": e.std_return,
                 "n": len(e.episode_returns), "returns": list(e.episode_returns)} for e in run.evaluations]
    by_step: dict[int, list] = {}
    for e in run.eval_episodes():
        by_step.setdefault(e.global_step, []).append(e.episode_return)
    return [{"global_step": s, "mean": float(np.mean(v)), "std": float(np.std(v)), "n": len(v),
             "returns": v} for s, v in sorted(by_step.items())]


def cross_check(run: RunData, episodes: list[Episode] | None = None) -> dict:
    """Published training returns vs returns summed from the recorded transitions."""
    if run.transitions is None or len(run.transitions) == 0:
        return {"checked": 0, "max_abs_diff": None, "mismatches": [], "missing": 0}
    eps = episodes if episodes is not None else reconstruct_episodes(run.transitions)
    summed = {e.episode_id: e for e in eps if e.complete}
    diffs, mism, missing = [], [], 0
    for s in run.train_episodes():
        e = summed.get(s.episode_id)
        if e is None:
            missing += 1
            continue
        d = abs(e.episode_return - s.episode_return)
        diffs.append(d)
        # float32 rewards in the transitions vs the float64 sum the agent publishes
        tol = 1e-5 * max(1.0, float(np.sum(np.abs(run.transitions.rewards[e.index]), dtype=np.float64))) + 1e-6
        if d > tol or e.length != s.length:
            mism.append({"episode_id": s.episode_id, "published": s.episode_return,
                         "from_transitions": e.episode_return, "published_length": s.length,
                         "transitions_length": e.length})
    return {"checked": len(diffs), "max_abs_diff": max(diffs) if diffs else None,
            "mismatches": mism, "missing": missing}


def run_summary(run: RunData, *, budget: float | None = None) -> dict:
    train = run.train_episodes()
    returns = [e.episode_return for e in train]
    final, k = final_performance(returns)
    progress = [e.global_frames or e.global_step for e in train]
    evals = eval_points(run)
    eps = reconstruct_episodes(run.transitions) if run.transitions is not None else []
    last_stats = run.stats[-1] if run.stats else None
    return {
        "run_id": run.run_id, "algorithm": run.algorithm, "env_id": run.env_id, "bags": run.bags,
        "train_episodes": len(train),
        "global_steps": max((e.global_step for e in train), default=0),
        "global_frames": max((e.global_frames for e in train), default=0),
        "final": {"mean": final, "n": k, "rule": "last 3 (under 25 episodes)" if k and len(train) < 25
                  else "last 10"},
        "terciles": tercile_summaries(progress, returns, budget=budget),
        "eval_points": [{k2: v for k2, v in p.items() if k2 != "returns"} for p in evals],
        "final_eval": evals[-1]["mean"] if evals else None,
        "episodes": [{"episode_id": e.episode_id, "return": e.episode_return, "length": e.length,
                      "terminated": e.terminated, "truncated": e.truncated,
                      "global_step": e.global_step, "global_frames": e.global_frames,
                      "wall_time_s": e.wall_time_s} for e in train],
        "transitions": len(run.transitions) if run.transitions is not None else 0,
        "reconstructed_episodes": sum(e.complete for e in eps),
        "noncontiguous_episodes": sum(not e.contiguous for e in eps),
        "cross_check": cross_check(run, eps),
        "memory_stats": last_stats,
        "warnings": list(run.warnings),
    }


def _ms(values) -> dict:
    v = np.asarray([x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))],
                   dtype=np.float64)
    return {"mean": float(v.mean()) if v.size else None, "std": float(v.std()) if v.size else None,
            "n": int(v.size)}


def group_summaries(summaries: list[dict]) -> list[dict]:
    """Mean +- std (population, ddof 0) across runs, grouped by (algorithm, env_id)."""
    groups: dict[tuple, list] = {}
    for s in summaries:
        groups.setdefault((s["algorithm"], s["env_id"]), []).append(s)
    out = []
    for (algo, env), runs in sorted(groups.items()):
        steps = sorted({p["global_step"] for r in runs for p in r["eval_points"]})
        curve = []
        for st in steps:
            vals = [p["mean"] for r in runs for p in r["eval_points"] if p["global_step"] == st]
            curve.append({"global_step": st, **_ms(vals)})
        out.append({
            "algorithm": algo, "env_id": env, "runs": [r["run_id"] for r in runs],
            "final": _ms([r["final"]["mean"] for r in runs]),
            "terciles": [_ms([r["terciles"][k]["mean"] for r in runs]) for k in range(3)],
            "final_eval": _ms([r["final_eval"] for r in runs]),
            "eval_curve": curve,
        })
    return out
