#!/usr/bin/env python3
"""Lock-step simulation throughput: gymnasium direct vs the comper_sim node over ROS 2.

For each environment, in one run and with the same random actions:
  direct      gymnasium env.step in this process (ALE: frameskip 5, sticky 0.25, full action set;
              its own observation, no 84x84 preprocessing)
  core        comper_sim.core.SimBridge.step_many in this process (the bridge, preprocessing included)
  ros step    the sim node in a separate process (`ros2 run comper_sim sim_node`), one ~/step call
              per step
  ros K=...   the same node, ~/step_many with K actions per call (transitions back as one
              TransitionBatch, converted to numpy on arrival)
Prints steps/s (best and median of interleaved rounds) and the ratio to direct. Episodes reset
automatically everywhere.

    . ./env.sh && python benchmarks/sim_bench.py
    python benchmarks/sim_bench.py --envs Hopper-v4 --steps 20000 --k 100 1000 --json benchmarks/out/sim.json
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEFAULT_STEPS = {"Hopper-v4": 10_000, "ALE/Freeway-v5": 2_000}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--envs", nargs="+", default=["Hopper-v4", "ALE/Freeway-v5"], help="gymnasium ids")
    p.add_argument("--steps", type=int, default=0,
                   help="steps per measurement (0: 10000 for vector tasks, 2000 for ALE)")
    p.add_argument("--single-steps", type=int, default=0,
                   help="steps through the single-step service (0: steps / 4)")
    p.add_argument("--k", type=int, nargs="+", default=[100, 1000], help="actions per step_many call")
    p.add_argument("--frame-stack", type=int, default=1, help="ALE frame_stack of the node and the core")
    p.add_argument("--repeats", type=int, default=3, help="interleaved rounds per path (best and median reported)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="also write the results here")
    return p.parse_args(argv)


def random_actions(info, n, rng):
    if info.discrete:
        return rng.integers(0, info.num_actions, n).astype(np.float32)
    return rng.uniform(info.action_low, info.action_high, (n, *info.action_shape)).astype(np.float32)


def bench_direct(env_id, actions, seed):
    import gymnasium as gym
    if env_id.startswith("ALE/"):
        import ale_py
        gym.register_envs(ale_py)
        env = gym.make(env_id, frameskip=5, repeat_action_probability=0.25, full_action_space=True)
        acts = actions.astype(np.int64)
    else:
        env = gym.make(env_id)
        acts = actions
    env.reset(seed=seed)
    step, reset = env.step, env.reset
    t0 = time.perf_counter()
    for a in acts:
        _, _, term, trunc, _ = step(a)
        if term or trunc:
            reset()
    dt = time.perf_counter() - t0
    env.close()
    return len(acts) / dt


def bench_core(config, actions, k):
    from comper_sim.core import SimBridge
    b = SimBridge(config)
    b.reset()
    t0 = time.perf_counter()
    for i in range(0, len(actions), k):
        b.step_many(actions[i:i + k], autoreset=True)
    dt = time.perf_counter() - t0
    b.close()
    return len(actions) / dt


class RemoteSim:
    """The sim node in its own process, started with `ros2 run`, and a client node here."""

    def __init__(self, env_id, frame_stack, seed, log_dir):
        import rclpy
        from rclpy.node import Node

        from comper_msgs.srv import EnvInfo, Reset, Step, StepMany
        ros2 = shutil.which("ros2")
        if ros2 is None:
            sys.exit("no ros2 command on PATH: source env.sh first (. ./env.sh in the workspace root)")
        self.name = f"bench_sim_{os.getpid()}_{env_id.replace('/', '_').replace('-', '_')}"
        self.log_path = Path(log_dir) / f"{self.name}.log"
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            [ros2, "run", "comper_sim", "sim_node", "--ros-args", "-p", f"env_id:={env_id}",
             "-p", f"frame_stack:={frame_stack}", "-p", f"seed:={seed}", "-r", f"__node:={self.name}",
             "--log-level", "warn"],
            stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(f"bench_client_{os.getpid()}", context=self.context)
        from rclpy.executors import SingleThreadedExecutor
        self.executor = SingleThreadedExecutor(context=self.context)   # never the global executor
        self.executor.add_node(self.node)
        self.types = (Reset, Step, StepMany, EnvInfo)
        self.reset_c = self.node.create_client(Reset, f"/{self.name}/reset")
        self.step_c = self.node.create_client(Step, f"/{self.name}/step")
        self.many_c = self.node.create_client(StepMany, f"/{self.name}/step_many")
        for c in (self.reset_c, self.step_c, self.many_c):
            if not c.wait_for_service(timeout_sec=60):
                self.close()
                sys.exit(f"sim node did not come up; its log:\n{self.log_path.read_text(errors='replace')}")

    def call(self, client, req):
        fut = client.call_async(req)
        # a plain spin_once loop: in rclpy 7.1 Executor.spin_until_future_complete adds ~10 ms
        # per call here (measured), which would be charged to the node
        deadline = time.monotonic() + 120
        spin_once = self.executor.spin_once
        while not fut.done() and time.monotonic() < deadline:
            spin_once(timeout_sec=1.0)
        res = fut.result()
        if res is None or not res.success:
            raise RuntimeError(f"{client.srv_name}: {getattr(res, 'message', 'no answer')}")
        return res

    def reset(self):
        return self.call(self.reset_c, self.types[0].Request(seed=-1))

    def bench_single(self, actions):
        from comper_msgs_py.convert import array_to_numpy, numpy_to_array
        Step = self.types[1]
        self.reset()
        req = Step.Request()
        t0 = time.perf_counter()
        for a in actions:
            numpy_to_array(a, req.action)
            res = self.call(self.step_c, req)
            array_to_numpy(res.observation)
            if res.terminated or res.truncated:
                self.reset()
        return len(actions) / (time.perf_counter() - t0)

    def bench_many(self, actions, k):
        from comper_msgs_py.convert import array_to_numpy, batch_to_transitions, numpy_to_array
        StepMany = self.types[2]
        self.reset()
        t0 = time.perf_counter()
        for i in range(0, len(actions), k):
            req = StepMany.Request(autoreset=True)
            numpy_to_array(actions[i:i + k], req.actions)
            res = self.call(self.many_c, req)
            batch_to_transitions(res.transitions)
            array_to_numpy(res.observation)
        return len(actions) / (time.perf_counter() - t0)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()


def main(argv=None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(101, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from comper_msgs_py.params import config_from_dict
    from comper_sim.core import SimBridge, SimConfig

    results = []
    log_dir = tempfile.mkdtemp(prefix="sim_bench_")
    print(f"# sim_bench: {' '.join(sys.argv)}  (python {sys.version.split()[0]}, {os.cpu_count()} cpus, "
          f"load average {os.getloadavg()[0]:.1f} at start, ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}, "
          f"node logs in {log_dir})")
    print(f"# {args.repeats} interleaved rounds per path; best = fastest round (least disturbed by other "
          "load), ratio = best / best direct")
    header = f"{'env':<16} {'path':<24} {'steps':>7} {'best/s':>9} {'median/s':>9} {'x direct':>9}"
    print(header)
    print("-" * len(header))
    for env_id in args.envs:
        n = args.steps or DEFAULT_STEPS.get(env_id, 2_000 if env_id.startswith("ALE/") else 10_000)
        n_single = args.single_steps or max(1, n // 4)
        config = config_from_dict(SimConfig, {"env_id": env_id, "seed": args.seed, "frame_stack": args.frame_stack})
        probe = SimBridge(config)
        info = probe.info()
        probe.close()
        rng = np.random.default_rng(args.seed)
        actions = random_actions(info, n, rng)
        paths = {"gymnasium direct": (n, lambda: bench_direct(env_id, actions, args.seed)),
                 f"core step_many K={max(args.k)}": (n, lambda: bench_core(config, actions, max(args.k)))}
        remote = RemoteSim(env_id, args.frame_stack, args.seed, log_dir)
        paths["ros ~/step"] = (n_single, lambda: remote.bench_single(actions[:n_single]))
        for k in args.k:
            paths[f"ros ~/step_many K={k}"] = (n, lambda k=k: remote.bench_many(actions, k))
        rates: dict[str, list[float]] = {name: [] for name in paths}
        try:
            for _ in range(args.repeats):
                for name, (_, fn) in paths.items():
                    rates[name].append(fn())
        finally:
            remote.close()
        direct = max(rates["gymnasium direct"])
        for name, (steps, _) in paths.items():
            best, median = max(rates[name]), float(np.median(rates[name]))
            print(f"{env_id:<16} {name:<24} {steps:>7} {best:>9.0f} {median:>9.0f} {best / direct:>9.2f}", flush=True)
            results.append({"env_id": env_id, "path": name, "steps": steps, "rounds": rates[name],
                            "best_steps_per_s": best, "median_steps_per_s": median,
                            "ratio_to_direct": best / direct})
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"argv": sys.argv, "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
