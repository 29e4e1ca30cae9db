"""qt_trainer_node and memory_node in separate processes (ros2 run): a reduce round trip trains QT,
upserts RTM and publishes a QTModel whose predictions, rebuilt in this (learner) process, match
the predictions the RTM stored; an empty TM reduces to nothing; a missing memory is reported."""
import os
import re
import time

import numpy as np
import pytest

from comper_msgs.msg import QTModel
from comper_msgs.srv import Reduce, Sample, Store
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import batch_to_transitions, transitions_to_batch
from comper_agent.nodes.qt_trainer_node import QT_MODEL_QOS, msg_to_qt
from comper_memory.core import transition_keys
from conftest import call, spin_once


def _transitions(n, seed=0):
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(n, 11)).astype(np.float32)
    return Transitions(states=s, actions=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                       rewards=rng.normal(size=n).astype(np.float32),
                       next_states=(s + 0.1).astype(np.float32), terminated=np.zeros(n, bool),
                       truncated=np.zeros(n, bool), value_labels=(s[:, 0] * 3 + 1).astype(np.float32))


def test_reduce_round_trip_publishes_a_model_that_predicts_like_the_rtm(launch, ros_node):
    tag = os.getpid()
    mem, qt = f"mem_{tag}", f"qt_{tag}"
    launch("comper_memory", "memory_node", "--ros-args", "-r", f"__node:={mem}", name=mem)
    trainer = launch("comper_agent", "qt_trainer_node", "--ros-args", "-p", f"memory_node:={mem}",
                     "-p", "qt_epochs:=3", "-r", f"__node:={qt}", name=qt)
    models = []
    ros_node.create_subscription(QTModel, f"/{qt}/qt_model", models.append, QT_MODEL_QOS)
    store = ros_node.create_client(Store, f"/{mem}/store")
    sample = ros_node.create_client(Sample, f"/{mem}/sample")
    reduce = ros_node.create_client(Reduce, f"/{qt}/reduce")

    t = _transitions(300)
    req = Store.Request()
    transitions_to_batch(t, req.batch)
    assert call(ros_node, store, req, timeout=60).success

    r = call(ros_node, reduce, Reduce.Request(), timeout=60)
    assert r.success, r.message
    assert (r.sets_reduced, r.rtm_size, r.qt_version) == (300, 300, 1)
    assert np.isfinite(r.qt_loss) and r.duration_s > 0
    # the answer says where the round's time went
    split = re.fullmatch(r"reduced 300 sets: lease (\S+) s, QT (\S+) s, commit (\S+) s, model (\S+) s", r.message)
    assert split and sum(map(float, split.groups())) == pytest.approx(r.duration_s, abs=0.02), r.message
    deadline = time.monotonic() + 20
    while not models and time.monotonic() < deadline:
        spin_once(ros_node)
    assert models, f"no QTModel received:\n{trainer.log()}"
    msg = models[-1]
    assert msg.version == 1 and msg.architecture == "comcact" and msg.key_size == 11 + 3 + 1 + 11
    model = msg_to_qt(msg)

    s = call(ros_node, sample, Sample.Request(batch_size=64, source=Sample.Request.SOURCE_RTM, seed=1))
    assert s.success, s.message
    batch = batch_to_transitions(s.batch)
    local = model.predict_transitions(batch, transition_keys)
    np.testing.assert_allclose(local, batch.value_labels, rtol=1e-4, atol=1e-4 * max(1.0, np.abs(local).max()))

    r2 = call(ros_node, reduce, Reduce.Request(), timeout=60)
    assert r2.success and r2.sets_reduced == 0 and r2.rtm_size == 300 and r2.qt_version == 1
    assert "empty" in r2.message


def test_reduce_without_a_memory_node_says_what_to_do(launch, ros_node):
    qt = f"qt_nomem_{os.getpid()}"
    launch("comper_agent", "qt_trainer_node", "--ros-args", "-p", "memory_node:=no_such_memory",
           "-r", f"__node:={qt}", name=qt)
    reduce = ros_node.create_client(Reduce, f"/{qt}/reduce")
    r = call(ros_node, reduce, Reduce.Request(), timeout=60)
    assert not r.success
    assert "no_such_memory" in r.message and "memory_node:=" in r.message


def test_a_reduction_whose_lease_ran_out_is_reported_and_its_sets_go_back_to_tm(launch, ros_node):
    """A QT round longer than the memory's lease_timeout_s (a slow machine) must not end the learner's run:
    the trainer answers success with 0 sets reduced and says why, publishes the QT it trained, and the
    sets are back in TM for the next reduction."""
    from comper_msgs.srv import GetStats
    tag = os.getpid()
    mem, qt = f"mem_lease_{tag}", f"qt_lease_{tag}"
    launch("comper_memory", "memory_node", "--ros-args", "-p", "lease_timeout_s:=0.001", "-r", f"__node:={mem}",
           name=mem)
    trainer = launch("comper_agent", "qt_trainer_node", "--ros-args", "-p", f"memory_node:={mem}",
                     "-p", "qt_epochs:=3", "-r", f"__node:={qt}", name=qt)
    models = []
    ros_node.create_subscription(QTModel, f"/{qt}/qt_model", models.append, QT_MODEL_QOS)
    req = Store.Request()
    transitions_to_batch(_transitions(300), req.batch)
    assert call(ros_node, ros_node.create_client(Store, f"/{mem}/store"), req, timeout=60).success

    r = call(ros_node, ros_node.create_client(Reduce, f"/{qt}/reduce"), Reduce.Request(), timeout=60)
    assert r.success, r.message
    assert (r.sets_reduced, r.rtm_size, r.qt_version) == (0, 0, 1)
    assert "300 sets trained on but not committed" in r.message and "lease_timeout_s" in r.message
    deadline = time.monotonic() + 20
    while not models and time.monotonic() < deadline:
        spin_once(ros_node)
    assert models and models[-1].version == 1, trainer.log()
    st = call(ros_node, ros_node.create_client(GetStats, f"/{mem}/get_stats"), GetStats.Request(), timeout=30)
    assert st.stats.tm_sets == 300 and st.stats.rtm_size == 0
