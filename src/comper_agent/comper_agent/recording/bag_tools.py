"""Bag tools: replay a bag's transitions into a memory node; export a Minari dataset; repair.

    ros2 run comper_agent bag_to_memory runs/hopper-s0 [--memory-node memory_node] [--batch 1024]
    ros2 run comper_agent export_dataset runs/hopper-s0 [--dataset-id comper/Hopper/hopper-s0-v0]
    ros2 run comper_agent evaluate --repair runs/hopper-s0 --out -      # bag_repair_main, below

A bag that cannot be read ends in one line naming it and the repair to run.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from comper_msgs_py.arrays import Transitions

from comper_agent.offline import runs as offline

__all__ = ["bag_to_memory_main", "export_dataset_main", "export_minari", "default_dataset_id", "iter_batches",
           "load_transitions", "bag_repair_main"]


def _read_runs(paths):
    """offline.read_runs, with an unreadable bag reported as one line naming it and the repair."""
    from comper_agent.offline.evaluate import _check_readable
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
# Minari export
_REWARD_NOTE = ("raw environment rewards as the environment returned them (game score changes for Atari), "
                "stored float32; not clipped: COMPER's reward_clip applies inside its learner only")


def _run_config(run) -> dict:
    """config.yaml of the run directory holding one of the run's bags (runs/<id>/bag), else {}."""
    import yaml
    for bag in run.bags:
        f = Path(bag).parent / "config.yaml"
        if f.is_file():
            try:
                return yaml.safe_load(f.read_text()) or {}
            except yaml.YAMLError:
                return {}
    return {}


def _suite_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("comper_agent")
    except PackageNotFoundError:
        return "unknown"


def _env_spec(env_id: str):
    """The gymnasium EnvSpec of env_id (ALE ids once ale_py registered them), or None."""
    import gymnasium as gym
    if not env_id:
        return None
    if env_id.startswith("ALE/"):
        try:
            import ale_py
            gym.register_envs(ale_py)
        except ImportError:
            return None
    try:
        return gym.spec(env_id)
    except gym.error.Error:
        return None


def _spaces(t: Transitions, env_cfg: dict):
    """Observation and action spaces of the data as stored: the bag's dtypes and shapes; action bounds
    (continuous) or count (discrete) from the run's config.yaml env description when present."""
    from gymnasium import spaces
    s = t.states
    obs = (spaces.Box(0, 255, s.shape[1:], np.uint8) if s.dtype == np.uint8
           else spaces.Box(-np.inf, np.inf, s.shape[1:], np.float32))
    a = np.asarray(t.actions)
    if a.ndim == 1:   # discrete: action indices
        n = int(env_cfg.get("num_actions") or int(a.max()) + 1)
        return obs, spaces.Discrete(n)
    lo, hi = env_cfg.get("action_low"), env_cfg.get("action_high")
    if lo is not None and hi is not None and np.shape(lo) == a.shape[1:]:
        return obs, spaces.Box(np.asarray(lo, np.float32), np.asarray(hi, np.float32), a.shape[1:], np.float32)
    return obs, spaces.Box(-np.inf, np.inf, a.shape[1:], np.float32)


def default_dataset_id(run) -> str:
    """comper/<task>/<run id>-v0 (Minari ids: (namespace/)name-v<version>; other characters become _)."""
    import re
    task = re.sub(r"-v\d+$", "", (run.env_id or "unknown").split("/")[-1])
    task, name = (re.sub(r"[^-\w]+", "_", x).strip("_") or "x" for x in (task, run.run_id))
    return f"comper/{task}/{name}-v0"


def export_minari(paths, *, dataset_id: str | None = None, run_id: str | None = None,
                  include_incomplete: bool = False, description: str | None = None) -> list[dict]:
    """Write each run's recorded episodes as a Minari dataset (hdf5) under MINARI_DATASETS_PATH.

    Episodes come from the transitions (``offline.reconstruct_episodes``): observations [T+1] (the last
    is the final next_state), actions [T], rewards [T], terminations [T] and truncations [T] kept apart.
    Paths are bags or run directories; a run directory's config.yaml supplies the seed, the env
    description (action bounds, number of actions) and the learner's reward clipping. Incomplete trailing
    episodes (cut by the end of the recording) are left out unless include_incomplete, and so are episodes
    with steps missing from the recording (not contiguous: no observation sequence). A dataset id that
    exists is refused before anything is written; a failed export removes what it created. Returns one
    summary dict per dataset."""
    import warnings

    import minari
    from minari.data_collector import EpisodeBuffer
    from minari.storage import get_dataset_path

    runs = {rid: r for rid, r in sorted(_read_runs(paths).items())
            if (run_id is None or rid == run_id) and r.transitions is not None and len(r.transitions)}
    if not runs:
        raise ValueError(f"no transitions{' for run ' + run_id if run_id else ''} in {', '.join(map(str, paths))}")
    if dataset_id and len(runs) > 1:
        raise ValueError(f"--dataset-id names one dataset but the bags hold {len(runs)} runs "
                         f"({', '.join(runs)}); pick one with --run-id")
    ids = {rid: dataset_id or default_dataset_id(run) for rid, run in runs.items()}
    for did in ids.values():    # every id checked before anything is written
        minari.dataset.minari_dataset.parse_dataset_id(did)   # ValueError: malformed id
        if Path(get_dataset_path(did)).exists():
            raise ValueError(f"Minari dataset {did} exists already ({get_dataset_path(did)}); choose another "
                             "--dataset-id or version")
    out = []
    for rid, run in runs.items():
        did = ids[rid]
        target = Path(get_dataset_path(did))
        t = run.transitions
        cfg = _run_config(run)
        params, env_cfg = cfg.get("params") or {}, cfg.get("env") or {}
        obs_space, act_space = _spaces(t, env_cfg)
        discrete = act_space.shape == ()     # Discrete
        buffers, episodes, gaps = [], [], 0
        for e in offline.reconstruct_episodes(t):
            if not e.complete and not include_incomplete:
                continue
            if not e.contiguous:   # steps missing from the recording: no observation sequence to give
                gaps += 1
                continue
            i = e.index
            a = np.asarray(t.actions[i])
            buffers.append(EpisodeBuffer(
                id=len(buffers), observations=np.concatenate([t.states[i], t.next_states[i[-1:]]]),
                actions=a.astype(np.int64) if discrete else a.astype(np.float32),
                rewards=np.asarray(t.rewards[i], np.float32), terminations=np.asarray(t.terminated[i], bool),
                truncations=np.asarray(t.truncated[i], bool)))
            episodes.append({"run_id": rid, "episode_id": e.episode_id, "length": e.length,
                             "return": e.episode_return, "complete": e.complete,
                             "first_step": int(t.steps[i[0]]) if t.steps.size else -1})
        if not buffers:
            raise ValueError(f"run {rid}: no complete episode to export (--include-incomplete exports cut ones)")
        spec = _env_spec(run.env_id)
        learner = cfg.get("learner") or {}
        seed = learner.get("seed", params.get("seed"))   # the learners keep it in their learner config
        comper = {"run_id": rid, "env_id": run.env_id, "algorithm": run.algorithm, "seed": seed,
                  "suite_version": _suite_version(), "source_bags": [str(b) for b in run.bags],
                  "rewards": _REWARD_NOTE, "reward_clip_in_learner": learner.get("reward_clip"),
                  "observations": f"{t.states.dtype} {list(t.states.shape[1:])} as recorded (the agent's "
                                  "observation after its preprocessing)",
                  "episode_metadata": "each episode's metadata: run_id, episode_id (the agent's), length, "
                                      "return (float64 sum), complete, first_step",
                  "episodes_left_out_with_gaps": gaps}
        try:
            with warnings.catch_warnings():
                # minari's notes on optional fields (author, code_permalink, eval_env) are not errors here
                warnings.filterwarnings("ignore", category=UserWarning, module=r"minari\.")
                ds = minari.create_dataset_from_buffers(
                    did, buffers, env=spec, algorithm_name=run.algorithm or None,
                    observation_space=obs_space, action_space=act_space, data_format="hdf5",
                    description=description or (f"{run.algorithm or 'agent'} training run {rid} on {run.env_id}, "
                                                "exported from its rosbag2 recording by comper_agent "
                                                "export_dataset"),
                    jpeg_encoding=False)
                ds.storage.update_metadata({"comper": comper})
                ds.storage.update_episode_metadata(episodes, range(len(episodes)))
        except BaseException:
            import shutil
            shutil.rmtree(target, ignore_errors=True)
            raise
        out.append({"dataset_id": did, "path": str(target), "run_id": rid, "env_id": run.env_id,
                    "env_spec": spec is not None, "total_episodes": ds.total_episodes,
                    "total_steps": ds.total_steps, "seed": seed, "left_out_with_gaps": gaps})
    return out


def export_dataset_main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ros2 run comper_agent export_dataset",
        description="Export recorded runs (bags or run directories) as Minari datasets (hdf5), one per run, "
                    "into MINARI_DATASETS_PATH (default ~/.minari/datasets); load them with "
                    "minari.load_dataset(ID).")
    p.add_argument("paths", nargs="+", help="bag or run directories")
    p.add_argument("--dataset-id", help="Minari dataset id (namespace/name-v<version>; default "
                                        "comper/<task>/<run id>-v0); only with a single run")
    p.add_argument("--datasets-path", help="Minari's datasets root (sets MINARI_DATASETS_PATH for this export)")
    p.add_argument("--run-id", help="only this run")
    p.add_argument("--include-incomplete", action="store_true",
                   help="also export episodes cut by the end of the recording")
    p.add_argument("--description", help="dataset description (default: algorithm, run, task)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.datasets_path:
        import os
        os.environ["MINARI_DATASETS_PATH"] = str(Path(args.datasets_path).resolve())
    try:
        made = export_minari(args.paths, dataset_id=args.dataset_id, run_id=args.run_id,
                             include_incomplete=args.include_incomplete, description=args.description)
    except (FileNotFoundError, ValueError) as exc:
        print(f"export_dataset: {exc}", file=sys.stderr)
        return 1
    for d in made:
        gaps = f" ({d['left_out_with_gaps']} episodes with missing steps left out)" if d["left_out_with_gaps"] else ""
        print(f"{d['run_id']}: {d['total_episodes']} episodes, {d['total_steps']} steps{gaps} -> Minari dataset "
              f"{d['dataset_id']} ({d['path']}); minari.load_dataset({d['dataset_id']!r})")
    return 0


# --------------------------------------------------------------------------------------------
def bag_repair_main(argv=None) -> int:
    """Rebuild the metadata.yaml of bags whose recorder was killed (comper_agent.recording.bags.repair_bag)."""
    from comper_agent.offline.evaluate import repair_command
    p = argparse.ArgumentParser(
        prog="bag_repair",
        description="Rebuild each bag's metadata.yaml from its complete storage files; a partial file (the one "
                    "being written when the recorder died) is moved to <bag>/.open/, untouched.")
    p.add_argument("paths", nargs="+", help="bag or run directories")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    return repair_command(args.paths, "bag_repair")
