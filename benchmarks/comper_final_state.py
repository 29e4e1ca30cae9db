#!/usr/bin/env python3
"""The QT diagnostics of finished comper_node runs (comper, comper_m) at their last checkpoint, offline.

For each run folder it rebuilds, without ROS, what the learner had at its last checkpoint: the Q-network
(config.yaml's learner section, latest.pt's learner state), the QT model (latest.pt's qt_trainer state)
and the memory (config.yaml's memory section, restored from the snapshot the checkpoint names; a run
written with checkpoint_replay). It then draws --batches batches of the learner's batch size from the
run's sampling source as the learner does (uniform; RTM for comper, TM for comper_m), predicts QT's
targets, and prints per run the mean over the batches of ``ComperLearner.qt_diagnostics`` and the
sampled-entry figures: the fields of a ``qt_diagnostics`` record (docs/comper.md, QT diagnostics), so a
run that finished before comper_node wrote them gets the figures of its final state.

    python benchmarks/comper_final_state.py runs/comper-Seaquest-s0 --json final_state.json

Restoring a 100,000-frame Atari memory rebuilds its index (about half a minute, 3 GB at its peak).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from bench_args import checkpoint_replay, last_checkpoint, offline_parser, rows_per_run


def final_state(run: Path, batches: int, seed: int) -> dict:
    import torch
    from comper_agent.core.comper import ComperLearner
    from comper_agent.core.config import ComperConfig
    from comper_agent.core.qt import QTModel
    from comper_agent.nodes.qt_diagnostics import sampled_entry_stats
    from comper_memory.core import CompactMemory, MemoryConfig, transition_keys
    from comper_msgs_py.params import config_from_dict

    cfg, ckpt, state = last_checkpoint(run, ("comper", "comper_m"), "has no QT target")
    kind, snap = checkpoint_replay(ckpt, state)
    if kind != "memory":
        raise ValueError(f"{run}: its last checkpoint holds no memory snapshot (checkpoint_replay)")
    torch.set_num_threads(1)
    learner = ComperLearner(config_from_dict(ComperConfig, cfg["learner"]),
                            obs_shape=tuple(cfg["env"]["observation_shape"]), n_actions=cfg["env"]["num_actions"])
    learner.load_state_dict(state["learner"])
    qt = QTModel.from_state_dict(state["qt_trainer"]["qt"])
    mem_cfg = {**cfg["memory"], "storage_dir": ""}      # in memory only: no log, no snapshots written
    memory = CompactMemory(config_from_dict(MemoryConfig, mem_cfg))
    memory.load_snapshot(str(snap))
    source = "tm" if cfg["algorithm"] == "comper_m" else "rtm"
    rng = np.random.default_rng(seed)
    step = int(state["counters"]["step"])
    recs = []
    for _ in range(batches):
        got = memory.sample(learner.config.batch_size, source, rng=rng, allow_fewer=True)
        targets = qt.predict_transitions(got.transitions, transition_keys)
        rec = learner.qt_diagnostics(got.transitions, targets)
        rec.update(sampled_entry_stats(step, got.transitions, got.counts))
        recs.append(rec)
    out = {k: float(np.nanmean([r[k] for r in recs])) for k in recs[0]}
    st = memory.stats()
    return {"run": run.name, "step": step, "frames": int(state["counters"].get("frames", 0)), "source": source,
            "batches": batches, **out, "memory": {k: st[k] for k in ("identities", "tm_sets", "rtm_size")}}


def main(argv=None) -> int:
    ap = offline_parser(__doc__, "comper_node run folders (comper or comper_m)")
    ap.add_argument("--batches", type=int, default=50, help="batches drawn per run (default %(default)s)")
    args = ap.parse_args(argv)
    return rows_per_run(
        args.runs, lambda run: final_state(run, args.batches, args.seed),
        lambda r: (f"{r['run']} (step {r['step']}, {r['frames']} frames, {r['batches']} batches from "
                   f"{r['source'].upper()}): "
                   + ", ".join(f"{k} {r[k]:.4g}" for k in ("qt_target_rmse", "td_rmse", "qt_bias", "label_bias",
                                                          "v_next_mean", "v_next_std", "qt_v_corr", "q_gap_mean",
                                                          "greedy_top_share", "label_age_mean",
                                                          "set_size_mean", "multi_member_fraction"))), args.json)


if __name__ == "__main__":
    sys.exit(main())
