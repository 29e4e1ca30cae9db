#!/usr/bin/env python3
"""Round trip of one ``<sim>/step`` service call inside one process, per executor layout.

    python benchmarks/transport_bench.py [--env-id Hopper-v4] [--steps 2000]

The embedded bring-up (comcact_node / comper_node) runs the learner loop in the main thread and
spins the nodes in background threads. This measures what one lock-step sim call costs with:
  direct      SimBridge.step in the same thread (no ROS): the floor
  per-node    each node its own SingleThreadedExecutor in its own thread (bringup.Spinner, the default)
  one-multi   one MultiThreadedExecutor(4) over both nodes (the layout before it was measured)
and prints ms per step and the ratio to per-node. Uses its own ROS domain (ROS_DOMAIN_ID 87 unless set).
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time

os.environ.setdefault("ROS_DOMAIN_ID", "87")
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def _measure_ros(layout: str, env_id: str, steps: int) -> float:
    import numpy as np
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from comper_agent.nodes.bringup import Spinner
    from comper_msgs_py.service_client import call
    from comper_msgs.srv import Reset, Step
    from comper_msgs_py.convert import numpy_to_array
    from comper_sim.sim_node import SimNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    name = f"transport_bench_sim_{os.getpid()}"
    sim = SimNode(name, context=ctx, parameter_overrides=[Parameter("env_id", value=env_id)])
    learner = Node(f"transport_bench_learner_{os.getpid()}", context=ctx)
    step_c = learner.create_client(Step, f"/{name}/step")
    reset_c = learner.create_client(Reset, f"/{name}/reset")
    if layout == "per-node":
        spinner = Spinner([sim, learner], ctx).start()
        stop = spinner.stop
    else:
        ex = MultiThreadedExecutor(num_threads=4, context=ctx)
        ex.add_node(sim)
        ex.add_node(learner)
        th = threading.Thread(target=ex.spin, daemon=True)
        th.start()

        def stop():
            ex.shutdown(timeout_sec=5)
            th.join(5)
    try:
        step_c.wait_for_service(timeout_sec=10)
        reset_c.wait_for_service(timeout_sec=10)
        call(reset_c, Reset.Request(seed=0))
        dim = int(sim.bridge.env.action_shape[0]) if sim.bridge.env.action_shape else 1
        act = np.zeros(dim, np.float32)

        def one():
            req = Step.Request()
            numpy_to_array(act, req.action)
            r = call(step_c, req)
            if r.terminated or r.truncated:
                call(reset_c, Reset.Request(seed=-1))
        for _ in range(100):
            one()
        t0 = time.perf_counter()
        for _ in range(steps):
            one()
        return (time.perf_counter() - t0) / steps
    finally:
        stop()
        learner.destroy_node()
        sim.destroy_node()
        rclpy.shutdown(context=ctx)


def _measure_direct(env_id: str, steps: int) -> float:
    import numpy as np

    from comper_sim.core import SimBridge, SimConfig
    b = SimBridge(SimConfig(env_id=env_id, seed=0))
    b.reset(0)
    act = np.zeros(b.env.action_shape[0] if b.env.action_shape else 1, np.float32)
    t0 = time.perf_counter()
    for _ in range(steps):
        if b.step(act).episode_over:
            b.reset(None)
    dt = (time.perf_counter() - t0) / steps
    b.close()
    return dt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env-id", default="Hopper-v4")
    ap.add_argument("--steps", type=int, default=2000, help="timed calls per layout (after 100 warm-up calls)")
    args = ap.parse_args(argv)
    res = {"direct": _measure_direct(args.env_id, args.steps)}
    for layout in ("per-node", "one-multi"):
        res[layout] = _measure_ros(layout, args.env_id, args.steps)
        print(f"  {layout:10s} {res[layout] * 1e3:7.3f} ms per step call", flush=True)
    base = res["per-node"]
    print(f"\n{args.env_id}, {args.steps} calls each:")
    for k, v in res.items():
        print(f"  {k:10s} {v * 1e3:7.3f} ms/step  ({v / base:.2f}x per-node)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
