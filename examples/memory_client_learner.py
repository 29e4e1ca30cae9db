#!/usr/bin/env python3
"""A learner of your own on the memory service, through MemoryClient (rclpy, numpy in and out): store Hopper-v4
transitions in batches of 64, reduce every 100 steps with the memory's newest-label predictor, sample 64 from RTM.

    ros2 run comper_memory memory_node --ros-args -p key_size:=26      # terminal 1
    . ./env.sh && python examples/memory_client_learner.py              # terminal 2

A QT trainer drives the two-phase reduction the same way: ``sets = memory.reduce_begin(); preds =
qt.fit_predict(sets.representatives, sets.histories()); memory.reduce_commit(sets.reduction_id,
sets.identity_ids, preds)``. For a plain replay buffer over the service see comper_memory.replay_buffer.
"""
import threading
import gymnasium as gym
import numpy as np
import rclpy
from rclpy.executors import MultiThreadedExecutor
from comper_memory.client import MemoryClient
from comper_msgs_py.arrays import Transitions

rclpy.init()
node = rclpy.create_node("toy_learner")
executor = MultiThreadedExecutor()
executor.add_node(node)
threading.Thread(target=executor.spin, daemon=True).start()   # the node is spun in the background
memory = MemoryClient(node, "memory_node", timeout=10.0)
assert memory.wait_for_service(10.0), "start memory_node first"

env = gym.make("Hopper-v4")
obs, _ = env.reset(seed=0)
rows = []
for step in range(2000):
    a = env.action_space.sample().astype(np.float32)
    nxt, r, term, trunc, _ = env.step(a)
    rows.append((obs, a, r, nxt, term, trunc))
    obs = env.reset()[0] if term or trunc else nxt
    if len(rows) == 64:                                 # one store call per 64 transitions
        s, a_, r_, n_, te, tr = map(np.asarray, zip(*rows))
        t = Transitions(s.astype(np.float32), a_, r_.astype(np.float32), n_.astype(np.float32),
                        te, tr, value_labels=np.zeros(64, np.float32))   # a real learner: V(s')
        memory.store(t)
        rows = []
    if step % 100 == 99:
        memory.reduce()                                 # or a QT trainer: reduce_begin/commit
        batch, ids, counts = memory.sample(64)          # uniform from RTM
        # ... learn on batch (batch.value_labels are the RTM predictions) ...
print(memory.stats())
executor.shutdown()
node.destroy_node()
rclpy.shutdown()
