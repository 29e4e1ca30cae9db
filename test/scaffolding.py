"""Test and benchmark scaffolding: synthetic runs, bags written without an agent, and an agent's
recording-contract publishers without an agent. Not part of the product (it lives under test/);
benchmarks import it by putting this folder on sys.path.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile

from comper_agent.recording.bags import ChunkedBagWriter, comper_typestore, make_qos
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.qos import RECORDED_QOS

__all__ = ["load_benchmark", "synthetic_run", "write_run_bag", "transitions_cdr", "episode_cdr", "evaluation_cdr",
           "EpisodeTopics", "env_run", "write_run_dir"]


BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_script(name: str):
    """scripts/<name>.py as a module (the set-up's helper scripts that tests check, e.g. docs_tables)."""
    path = BENCHMARKS.parent / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def load_benchmark(name: str):
    """benchmarks/<name>.py as a module, with benchmarks/ on sys.path while it loads (the scripts import
    bench_args and each other), so a test does not depend on another test having put it there."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return mod


def synthetic_run(n_steps: int, *, obs_dim: int = 11, action_dim: int = 3, seed: int = 0,
                  min_len: int = 20, max_len: int = 400, run_id: str = "synthetic") -> tuple[Transitions, list[dict]]:
    """A Hopper-like run: contiguous episodes (next_state[t] == state[t+1]), float64 rewards summed
    per episode as an agent publishes them. Returns (transitions, episode summaries as dicts)."""
    rng = np.random.default_rng(seed)
    lens = []
    total = 0
    while total < n_steps:
        k = int(min(rng.integers(min_len, max_len + 1), n_steps - total))
        lens.append(k)
        total += k
    states, next_states, actions, rewards, term, trunc, eids, steps = [], [], [], [], [], [], [], []
    summaries = []
    step = 0
    for eid, k in enumerate(lens):
        obs = rng.standard_normal((k + 1, obs_dim)).astype(np.float32)
        r64 = rng.normal(1.0, 0.5, k)           # what the environment returns (float64)
        states.append(obs[:-1])
        next_states.append(obs[1:])
        actions.append(rng.uniform(-1, 1, (k, action_dim)).astype(np.float32))
        rewards.append(r64.astype(np.float32))
        terminated = bool(rng.random() < 0.7) if k < max_len else False
        te = np.zeros(k, bool)
        tr = np.zeros(k, bool)
        (te if terminated else tr)[-1] = True
        term.append(te)
        trunc.append(tr)
        eids.append(np.full(k, eid, np.uint64))
        steps.append(np.arange(step, step + k, dtype=np.uint64))
        step += k
        ret = 0.0
        for x in r64:
            ret += float(x)
        summaries.append({"run_id": run_id, "episode_id": eid, "episode_return": ret, "length": k,
                          "frames": k, "terminated": terminated, "truncated": not terminated,
                          "global_step": step, "global_frames": step})
    t = Transitions(np.concatenate(states), np.concatenate(actions), np.concatenate(rewards),
                    np.concatenate(next_states), np.concatenate(term), np.concatenate(trunc),
                    value_labels=rng.standard_normal(step).astype(np.float32),
                    episode_ids=np.concatenate(eids), steps=np.concatenate(steps), run_id=run_id)
    return t, summaries


# --------------------------------------------------------------------------------------------
# building messages without rclpy (synthetic bags for tests and benchmarks, conversions)
def _ros_array(store, x):
    import numpy as np
    x = np.asarray(x)
    u8 = x.dtype == np.uint8
    return store.types["comper_msgs/msg/Array"](
        dtype=1 if u8 else 0, shape=np.asarray(x.shape, np.uint32),
        data_f32=np.zeros(0, np.float32) if u8 else np.ascontiguousarray(x, np.float32).ravel(),
        data_u8=np.ascontiguousarray(x).ravel() if u8 else np.zeros(0, np.uint8))


def _header(store, stamp_ns: int = 0):
    T = store.types
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
        sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9)), frame_id="")


def transitions_cdr(store, t, stamp_ns: int = 0) -> bytes:
    """comper_msgs_py.arrays.Transitions -> CDR bytes of a comper_msgs/TransitionBatch."""
    import numpy as np
    msg = store.types["comper_msgs/msg/TransitionBatch"](
        header=_header(store, stamp_ns), run_id=t.run_id, states=_ros_array(store, t.states),
        actions=_ros_array(store, np.asarray(t.actions, np.float32)),
        rewards=np.asarray(t.rewards, np.float32), next_states=_ros_array(store, t.next_states),
        terminated=np.asarray(t.terminated, bool), truncated=np.asarray(t.truncated, bool),
        value_labels=np.asarray(t.value_labels, np.float32), episode_ids=np.asarray(t.episode_ids, np.uint64),
        steps=np.asarray(t.steps, np.uint64))
    return bytes(store.serialize_cdr(msg, "comper_msgs/msg/TransitionBatch"))


def episode_cdr(store, stamp_ns: int = 0, **fields) -> bytes:
    """Keyword fields of comper_msgs/EpisodeSummary (missing ones default to 0 / '' / False)."""
    defaults = dict(run_id="", env_id="", source="train", episode_id=0, episode_return=0.0, length=0,
                    frames=0, terminated=False, truncated=False, global_step=0, global_frames=0, wall_time_s=0.0)
    defaults.update(fields)
    msg = store.types["comper_msgs/msg/EpisodeSummary"](header=_header(store, stamp_ns), **defaults)
    return bytes(store.serialize_cdr(msg, "comper_msgs/msg/EpisodeSummary"))


def evaluation_cdr(store, stamp_ns: int = 0, *, returns, lengths, **fields) -> bytes:
    import numpy as np
    r = np.asarray(returns, np.float64)
    defaults = dict(run_id="", algorithm="", env_id="", global_step=0)
    defaults.update(fields)
    msg = store.types["comper_msgs/msg/EvaluationResult"](
        header=_header(store, stamp_ns), episode_returns=r, episode_lengths=np.asarray(lengths, np.uint32),
        mean_return=float(r.mean()) if r.size else 0.0, std_return=float(r.std()) if r.size else 0.0, **defaults)
    return bytes(store.serialize_cdr(msg, "comper_msgs/msg/EvaluationResult"))


def write_run_bag(path, transitions, summaries, evaluations=(), *, agent: str = "comcact_node",
                  env_id: str = "Hopper-v4", algorithm: str = "comcact", storage: str = "mcap",
                  max_file_size_bytes: int = 256 * 2**20, compression: str = "zstd") -> Path:
    """Write a run as an agent + recorder would: per episode one TransitionBatch then its
    EpisodeSummary; evaluations: (global_step, returns, lengths)."""
    import numpy as np
    store = comper_typestore()
    ts = 1_700_000_000 * 10**9
    with ChunkedBagWriter(path, storage=storage, compression=compression, max_file_duration_s=0,
                          max_file_size_bytes=max_file_size_bytes,
                          custom_data={"run_id": transitions.run_id, "algorithm": algorithm}) as w:
        ht = w.add_topic(f"/{agent}/transitions", "comper_msgs/msg/TransitionBatch", [make_qos()])
        he = w.add_topic(f"/{agent}/episodes", "comper_msgs/msg/EpisodeSummary", [make_qos()])
        hv = w.add_topic(f"/{agent}/evaluations", "comper_msgs/msg/EvaluationResult", [make_qos()])
        evals = sorted(evaluations, key=lambda e: e[0])
        ids = np.asarray(transitions.episode_ids, np.int64)
        bounds = np.flatnonzero(np.diff(ids)) + 1
        starts = np.concatenate([[0], bounds])
        ends = np.concatenate([bounds, [len(transitions)]])
        for s, a, b in zip(summaries, starts, ends):
            ts += 10**6
            w.write(ht, ts, transitions_cdr(store, transitions.take(slice(int(a), int(b))), ts))
            w.write(he, ts, episode_cdr(store, ts, env_id=env_id, **s))
            while evals and evals[0][0] <= s["global_step"]:
                step, rets, lens = evals.pop(0)
                w.write(hv, ts, evaluation_cdr(store, ts, returns=rets, lengths=lens, run_id=transitions.run_id,
                                               algorithm=algorithm, env_id=env_id, global_step=int(step)))
    return Path(path)


def env_run(env_id: str, n_episodes: int, *, seed: int = 0, max_episode_steps: int | None = None,
            run_id: str = "env-run") -> tuple[Transitions, list[dict]]:
    """Real episodes: a gymnasium environment stepped with uniformly random actions (seeded), recorded as an
    agent records them (float32 observations and rewards, terminated and truncated apart, episode ids and
    global steps). Returns (transitions, episode summaries as dicts) like synthetic_run."""
    import gymnasium as gym
    env = gym.make(env_id, max_episode_steps=max_episode_steps)
    env.action_space.seed(seed)
    cols = {k: [] for k in ("s", "a", "r", "s2", "te", "tr", "eid", "step")}
    summaries, step = [], 0
    for eid in range(n_episodes):
        obs, _ = env.reset(seed=seed + eid)
        ret, k, done = 0.0, 0, False
        while not done:
            a = env.action_space.sample()
            obs2, r, term, trunc, _ = env.step(a)
            for key, v in zip(cols, (obs, a, r, obs2, term, trunc, eid, step)):
                cols[key].append(v)
            ret += float(r)
            obs, k, step, done = obs2, k + 1, step + 1, term or trunc
        summaries.append({"run_id": run_id, "episode_id": eid, "episode_return": ret, "length": k, "frames": k,
                          "terminated": bool(term), "truncated": bool(trunc) and not term, "global_step": step,
                          "global_frames": step})
    env.close()
    t = Transitions(np.asarray(cols["s"], np.float32), np.asarray(cols["a"], np.float32),
                    np.asarray(cols["r"], np.float32), np.asarray(cols["s2"], np.float32),
                    np.asarray(cols["te"], bool), np.asarray(cols["tr"], bool) & ~np.asarray(cols["te"], bool),
                    value_labels=np.zeros(step, np.float32), episode_ids=np.asarray(cols["eid"], np.uint64),
                    steps=np.asarray(cols["step"], np.uint64), run_id=run_id)
    return t, summaries


def write_run_dir(root, transitions, summaries, *, env_id: str, algorithm: str = "comcact", seed: int = 0,
                  env: dict | None = None, learner: dict | None = None) -> Path:
    """A run directory as a learner leaves it: <root>/<run_id>/config.yaml (algorithm, params with env_id, the
    env description, the learner config with its seed) and the run's bag in <root>/<run_id>/bag."""
    import yaml
    run = Path(root) / transitions.run_id
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump({
        "algorithm": algorithm, "params": {"env_id": env_id, "run_id": transitions.run_id, "eval_seed": -1},
        "env": {"env_id": env_id, **(env or {})}, "learner": {"seed": seed, **(learner or {})}}))
    write_run_bag(run / "bag", transitions, summaries, env_id=env_id, algorithm=algorithm)
    return run


class EpisodeTopics:
    """The publishers of the recording contract for an agent node (docs/recording.md)::

        topics = EpisodeTopics(self)                       # ~/transitions, ~/episodes, ~/evaluations
        topics.transitions(episode_transitions)            # Transitions with value_labels, episode_ids, steps
        topics.episode(run_id=..., env_id=..., source="train", episode_id=..., episode_return=..., ...)
        topics.evaluation(run_id=..., algorithm=..., env_id=..., global_step=..., returns=[...], lengths=[...])
    """

    def __init__(self, node: Node, prefix: str = "~", qos: QoSProfile = RECORDED_QOS):
        from comper_msgs.msg import EpisodeSummary, EvaluationResult, TransitionBatch
        self.node = node
        self._EpisodeSummary, self._EvaluationResult = EpisodeSummary, EvaluationResult
        self.transitions_pub = node.create_publisher(TransitionBatch, f"{prefix}/transitions", qos)
        self.episodes_pub = node.create_publisher(EpisodeSummary, f"{prefix}/episodes", qos)
        self.evaluations_pub = node.create_publisher(EvaluationResult, f"{prefix}/evaluations", qos)

    def transitions(self, t) -> None:
        from comper_msgs_py.convert import transitions_to_batch
        msg = transitions_to_batch(t)
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.transitions_pub.publish(msg)

    def episode(self, **fields) -> None:
        msg = self._EpisodeSummary()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        for k, v in fields.items():
            setattr(msg, k, v)
        self.episodes_pub.publish(msg)

    def evaluation(self, *, returns, lengths, **fields) -> None:
        import numpy as np
        msg = self._EvaluationResult()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        for k, v in fields.items():
            setattr(msg, k, v)
        r = np.asarray(returns, dtype=np.float64)
        msg.episode_returns = r.tolist()
        msg.episode_lengths = [int(x) for x in lengths]
        msg.mean_return = float(r.mean()) if r.size else 0.0
        msg.std_return = float(r.std()) if r.size else 0.0
        self.evaluations_pub.publish(msg)

    def destroy(self) -> None:
        for p in (self.transitions_pub, self.episodes_pub, self.evaluations_pub):
            self.node.destroy_publisher(p)
