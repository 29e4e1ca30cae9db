"""Checkpoints: atomic write, weights_only load, exact round trip (comper_agent.core.checkpoint)."""
import sys
from pathlib import Path

_SRC = Path(__file__).resolve().parents[2] / "src"
for _p in (_SRC / "comper_msgs", _SRC / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import numpy as np
import torch

from comper_msgs_py.arrays import Transitions
from comper_agent.core.checkpoint import load_checkpoint, save_checkpoint
from comper_agent.core.comcact import ComcactLearner
from comper_agent.core.comper import ComperLearner
from comper_agent.core.config import ComcactConfig, ComcactQTConfig, ComperConfig, DQNConfig
from comper_agent.core.qt import QTModel

torch.set_num_threads(1)   # tiny models; the shared 2-core machine is often busy


def cont_batch(n=32, seed=0):
    rng = np.random.default_rng(seed)
    return Transitions(states=rng.normal(size=(n, 3)).astype(np.float32),
                       actions=rng.uniform(-1, 1, size=(n, 1)).astype(np.float32),
                       rewards=rng.normal(size=n).astype(np.float32),
                       next_states=rng.normal(size=(n, 3)).astype(np.float32),
                       terminated=rng.random(n) < 0.2, truncated=np.zeros(n, bool))


def test_comcact_and_qt_round_trip(tmp_path):
    lrn = ComcactLearner(ComcactConfig(), 3, [-1.0], [1.0])
    b = cont_batch()
    lrn.update(b)
    lrn.qt_critic_step(b, np.ones(len(b), np.float32))
    lrn.soft_update()
    lrn.act(b.states[0])
    qt = QTModel(ComcactQTConfig())
    keys = np.random.default_rng(0).normal(size=(40, 8)).astype(np.float32)
    qt.fit(keys, np.arange(40, dtype=np.float32), np.ones(40, np.uint32))
    path = save_checkpoint(tmp_path / "ckpt" / "agent.pt",
                           {"learner": lrn.state_dict(), "qt": qt.state_dict(),
                            "qt_empty": QTModel().state_dict(),
                            "counters": {"step": 123, "frames": 456, "episode": 7}})
    assert [p.name for p in path.parent.iterdir()] == ["agent.pt"]      # no temp file left
    raw = torch.load(path, weights_only=True)                           # plain data only
    assert raw["state"]["counters"]["step"] == 123

    state = load_checkpoint(path)
    lrn2 = ComcactLearner(ComcactConfig(seed=5), 3, [-1.0], [1.0])
    lrn2.load_state_dict(state["learner"])
    qt2 = QTModel.from_state_dict(state["qt"])
    assert (lrn2.updates, lrn2.qt_steps) == (1, 1)
    np.testing.assert_array_equal(lrn2.value_labels(b), lrn.value_labels(b))
    np.testing.assert_array_equal(lrn2.td_targets(b).numpy(), lrn.td_targets(b).numpy())
    np.testing.assert_array_equal(qt2.predict(keys), qt.predict(keys))
    assert qt2.version == 1
    # training continues identically (optimiser states, noise and shuffling RNG restored)
    np.testing.assert_array_equal(lrn2.act(b.states[1]), lrn.act(b.states[1]))
    m1, m2 = lrn.update(b), lrn2.update(b)
    assert m1 == m2
    assert qt.fit(keys, np.arange(40, dtype=np.float32), np.ones(40, np.uint32)) == \
        qt2.fit(keys, np.arange(40, dtype=np.float32), np.ones(40, np.uint32))


def test_comper_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    b = Transitions(states=rng.integers(0, 256, (4, 4, 84, 84), dtype=np.uint8),
                    actions=rng.integers(0, 18, 4), rewards=np.ones(4, np.float32),
                    next_states=rng.integers(0, 256, (4, 4, 84, 84), dtype=np.uint8),
                    terminated=np.zeros(4, bool), truncated=np.zeros(4, bool))
    lrn = ComperLearner(DQNConfig())
    lrn.update(b)
    save_checkpoint(tmp_path / "c.pt", {"learner": lrn.state_dict()})
    lrn2 = ComperLearner(DQNConfig())
    lrn2.load_state_dict(load_checkpoint(tmp_path / "c.pt")["learner"])
    assert lrn2.updates == 1
    assert lrn.update(b) == lrn2.update(b)
    assert lrn.act(b.states[0], frames=0)[0] == lrn2.act(b.states[0], frames=0)[0]
