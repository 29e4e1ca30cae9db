"""Bag tools: replay a bag's transitions into a memory node; export an offline-RL dataset; repair.

    ros2 run comper_agent bag_to_memory runs/hopper-s0 [--memory-node memory_node] [--batch 1024]
    ros2 run comper_agent export_dataset runs/hopper-s0 --out datasets/hopper-s0
    ros2 run comper_agent evaluate --repair runs/hopper-s0 --out -      # bag_repair_main, below

A bag that cannot be read ends in one line naming it and the repair to run.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from comper_msgs_py.arrays import Transitions

from . import offline

__all__ = ["bag_to_memory_main", "export_dataset_main", "export_dataset", "iter_batches", "load_transitions",
           "bag_repair_main"]


def _read_runs(paths):
    """offline.read_runs, with an unreadable bag reported as one line naming it and the repair."""
    from .evaluate import _check_readable
    try:
        return offline.read_runs(paths)
    except Exception:  # noqa: BLE001 - name the bag and what to run, else the original error
        _check_readable(paths)
        raise


def load_transitions(paths, run_id: str | None = None) -> dict[str, Transitions]:
    runs = _read_runs(paths)
    out = {rid: r.transitions for rid, r in runs.items()
           if r.transitions is not None and len(r.transitions) and (run_id is None or rid == run_id)}
    if not out:
        raise ValueError(f"no transitions{' for run ' + run_id if run_id else ''} in {', '.join(map(str, paths))}")
    return out


def iter_batches(t: Transitions, batch: int):
    for i in range(0, len(t), batch):
        yield t.take(slice(i, i + batch))


# --------------------------------------------------------------------------------------------
def bag_to_memory_main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ros2 run comper_agent bag_to_memory",
        description="Replay the transitions of recorded bags (in step order, with their recorded value "
                    "labels) into a running memory_node through its store service "
                    "(comper_memory.client.MemoryClient).")
    p.add_argument("paths", nargs="+", help="bag or run directories")
    p.add_argument("--memory-node", default="memory_node", help="memory node name (default memory_node)")
    p.add_argument("--batch", type=int, default=1024, help="transitions per store call (default 1024)")
    p.add_argument("--run-id", help="only this run (default: every run in the bags)")
    p.add_argument("--label-fill", type=float, default=None,
                   help="value label for transitions recorded without labels (default: refuse such bags)")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the service / a reply")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.batch < 1:
        p.error("--batch must be >= 1")
    try:
        runs = load_transitions(args.paths, args.run_id)
    except (FileNotFoundError, ValueError) as exc:
        print(f"bag_to_memory: {exc}", file=sys.stderr)
        return 1
    for rid, t in runs.items():
        if t.value_labels.size != len(t):
            if args.label_fill is None:
                print(f"bag_to_memory: run {rid} has no value labels; pass --label-fill VALUE", file=sys.stderr)
                return 1
            t.value_labels = np.full(len(t), args.label_fill, np.float32)

    import rclpy

    from comper_memory.client import MemoryClient, MemoryServiceError

    rclpy.init(args=None)
    total = sum(len(t) for t in runs.values())
    done = 0
    t0 = time.perf_counter()
    try:
        with MemoryClient.standalone(args.memory_node, context=rclpy.get_default_context(),
                                     timeout=args.timeout) as memory:
            if not memory.wait_for_service(args.timeout):
                print(f"bag_to_memory: {args.memory_node}/store not available within {args.timeout} s",
                      file=sys.stderr)
                return 1
            before = memory.stats()["transitions_stored"]
            new_ids = 0
            for rid, t in runs.items():
                for b in iter_batches(t, args.batch):
                    reply = memory.store(b)
                    done += reply.stored
                    new_ids += reply.new_identities
                    rate = done / max(time.perf_counter() - t0, 1e-9)
                    print(f"\r[{rid}] stored {done}/{total} ({100.0 * done / total:5.1f} %, {rate:,.0f} transitions/s)",
                          end="", flush=True)
            after = memory.stats()
            print()
            print(f"stored {done} transitions ({new_ids} new identities) into {args.memory_node} in "
                  f"{time.perf_counter() - t0:.2f} s; memory now holds {after['transitions_stored']} "
                  f"(+{after['transitions_stored'] - before}), {after['identities']} identities")
    except (MemoryServiceError, TimeoutError, RuntimeError) as exc:
        print(f"\nbag_to_memory: {exc} (stored {done}/{total} before the error)", file=sys.stderr)
        return 1
    finally:
        rclpy.try_shutdown()
    return 0


# --------------------------------------------------------------------------------------------
def export_dataset(paths, out, *, run_id: str | None = None, include_incomplete: bool = False) -> dict:
    """Minari-like layout: <out>/<run_id>/episode_<id>.npz with observations [T+1, ...],
    actions [T, ...], rewards [T], terminations [T], truncations [T] (+ value_labels, steps),
    and <out>/manifest.json. npz without pickles (np.load(allow_pickle=False) reads them)."""
    runs = _read_runs(paths)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    manifest = {"format": "comper-offline-dataset", "format_version": 1,
                "layout": "per episode npz: observations [T+1], actions [T], rewards [T], terminations [T], "
                          "truncations [T], value_labels [T] (may be empty), steps [T]",
                "sources": [str(p) for p in paths], "datasets": []}
    for rid, run in sorted(runs.items()):
        if run_id is not None and rid != run_id:
            continue
        t = run.transitions
        if t is None or len(t) == 0:
            continue
        d = out / rid
        d.mkdir(parents=True, exist_ok=True)
        episodes = []
        for e in offline.reconstruct_episodes(t):
            if not e.complete and not include_incomplete:
                continue
            i = e.index
            obs = np.concatenate([t.states[i], t.next_states[i[-1:]]])
            name = f"episode_{e.episode_id:06d}.npz"
            np.savez(d / name, observations=obs, actions=np.asarray(t.actions[i]), rewards=t.rewards[i],
                     terminations=t.terminated[i], truncations=t.truncated[i],
                     value_labels=t.value_labels[i] if t.value_labels.size else np.zeros(0, np.float32),
                     steps=t.steps[i] if t.steps.size else np.zeros(0, np.uint64))
            episodes.append({"episode_id": e.episode_id, "file": f"{rid}/{name}", "length": e.length,
                             "return": e.episode_return, "terminated": e.terminated, "truncated": e.truncated,
                             "complete": e.complete, "contiguous": e.contiguous})
        manifest["datasets"].append({
            "run_id": rid, "env_id": run.env_id, "algorithm": run.algorithm,
            "total_episodes": len(episodes), "total_steps": int(sum(e["length"] for e in episodes)),
            "observation_shape": list(t.states.shape[1:]), "observation_dtype": str(t.states.dtype),
            "action_shape": list(t.actions.shape[1:]), "action_dtype": str(np.asarray(t.actions).dtype),
            "discrete_actions": bool(t.actions.ndim == 1), "episodes": episodes})
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def export_dataset_main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ros2 run comper_agent export_dataset",
        description="Export recorded transitions as a plain offline-RL dataset (Minari-like): one npz per "
                    "episode (observations [T+1], actions, rewards, terminations, truncations) and a JSON "
                    "manifest. No pickles.")
    p.add_argument("paths", nargs="+", help="bag or run directories")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--run-id", help="only this run")
    p.add_argument("--include-incomplete", action="store_true",
                   help="also export episodes cut by the end of the recording")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        m = export_dataset(args.paths, args.out, run_id=args.run_id, include_incomplete=args.include_incomplete)
    except (FileNotFoundError, ValueError) as exc:
        print(f"export_dataset: {exc}", file=sys.stderr)
        return 1
    for d in m["datasets"]:
        print(f"{d['run_id']}: {d['total_episodes']} episodes, {d['total_steps']} steps -> {args.out}/{d['run_id']}")
    print(f"manifest: {Path(args.out) / 'manifest.json'}")
    return 0


# --------------------------------------------------------------------------------------------
def bag_repair_main(argv=None) -> int:
    """Rebuild the metadata.yaml of bags whose recorder was killed (comper_agent.recording.repair_bag)."""
    from .evaluate import repair_command
    p = argparse.ArgumentParser(
        prog="bag_repair",
        description="Rebuild each bag's metadata.yaml from its complete storage files; a partial file (the one "
                    "being written when the recorder died) is moved to <bag>/.open/, untouched.")
    p.add_argument("paths", nargs="+", help="bag or run directories")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    return repair_command(args.paths, "bag_repair")
