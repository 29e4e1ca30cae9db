"""Learning regression tests: short, fixed-seed, CPU-deterministic runs of the comper_node learner
that must move well beyond the untrained network. The Atari one catches the optimiser defect
(batch-mean loss under Table 32's RMSProp constant, unclipped rewards); the CartPole one guards
the vector-task path and its profile.

* Atari: 2,500 random-play transitions of ALE/Asterix-v5 under the thesis protocol (frame skip 5,
  sticky actions, colour averaging), 200 updates of the thesis learner (NatureCNN, DeepMind's
  RMSProp, summed Huber loss, clipped rewards, target network): the greedy action must change in
  most held-out states. The old convention (mean loss, 0.01 constant, raw rewards) changes it in
  none, and moves the weights an order of magnitude less; both are asserted.
* CartPole-v1: the classic_control profile's DQN (MLP, learner + replay, no ROS) for 12,000 steps:
  greedy evaluation return at least 5x the untrained network's and >= 50.
"""
import sys
from pathlib import Path

_SRC = Path(__file__).resolve().parents[2] / "src"
for _p in (_SRC / "comper_msgs", _SRC / "comper_agent", _SRC / "comper_sim"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import numpy as np
import pytest
import torch

from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import config_from_dict
from comper_agent.core.comper import ComperLearner
from comper_agent.core.config import COMPER_PROFILES, ComperConfig, DQNConfig
from comper_agent.core.replay import ReplayBuffer

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def asterix_random_play():
    from comper_sim.core import SimConfig, make_env
    env = make_env(SimConfig(env_id="ALE/Asterix-v5", seed=0))
    rng = np.random.default_rng(0)
    cols = {k: [] for k in ("s", "a", "r", "ns", "term")}
    obs = env.reset(0)
    for _ in range(2500):
        a = int(rng.integers(18))
        nxt, r, term, trunc, _ = env.step(a)
        for k, v in zip(cols, (obs, a, r, nxt, term)):
            cols[k].append(v)
        obs = env.reset(None) if term or trunc else nxt
    env.close()
    data = Transitions(states=np.stack(cols["s"]), actions=np.asarray(cols["a"], np.float32),
                       rewards=np.asarray(cols["r"], np.float32), next_states=np.stack(cols["ns"]),
                       terminated=np.asarray(cols["term"], bool), truncated=np.zeros(2500, bool))
    assert data.rewards.max() >= 50 and (data.rewards > 0).sum() >= 10     # raw Asterix scores: 50 per item
    return data


def _train_on(data: Transitions, overrides: dict) -> tuple[float, float]:
    """(share of 500 held-out states whose greedy action changed, L2 distance the weights moved)."""
    lrn = ComperLearner(config_from_dict(ComperConfig, {"variant": "comper_f", "seed": 0, **overrides}))
    held = torch.as_tensor(data.states[2000:])
    with torch.no_grad():
        a0 = lrn.q(held).argmax(1).numpy()
    w0 = [p.detach().clone() for p in lrn.q.parameters()]
    rng = np.random.default_rng(1)
    for u in range(200):
        lrn.update(data.take(rng.integers(0, 2000, 32)))
        if u % 100 == 99:
            lrn.sync_target()
    with torch.no_grad():
        a1 = lrn.q(held).argmax(1).numpy()
    moved = float(torch.sqrt(sum(((p.detach() - q) ** 2).sum() for p, q in zip(lrn.q.parameters(), w0))))
    return float(np.mean(a1 != a0)), moved


@pytest.mark.slow
def test_thesis_learner_moves_its_greedy_policy_on_real_atari_frames(asterix_random_play):
    changed, moved = _train_on(asterix_random_play, {})
    # the defect: batch-mean loss with the unscaled 0.01 (= mean with 0.01 B^2 here) and raw rewards
    old_changed, old_moved = _train_on(asterix_random_play, {"loss_reduction": "mean",
                                                             "rms_min_sq_grad": 0.01 * 32 ** 2,
                                                             "reward_clip": "none"})
    assert changed >= 0.5, changed
    assert old_changed <= 0.05 and moved >= 10 * old_moved, (old_changed, moved, old_moved)


def _greedy_return(lrn, env, episodes=5) -> float:
    out = []
    for k in range(episodes):
        obs, _ = env.reset(seed=1000 + k)
        ret, done = 0.0, False
        while not done:
            obs, r, term, trunc, _ = env.step(lrn.act(obs.astype(np.float32), epsilon=0.0)[0])
            ret += r
            done = term or trunc
        out.append(ret)
    return float(np.mean(out))


@pytest.mark.slow
def test_classic_control_profile_dqn_learns_cartpole():
    import gymnasium as gym
    values = {k: v for k, (v, _) in COMPER_PROFILES["classic_control"].items()}
    c = config_from_dict(DQNConfig, {**values, "seed": 0}, ignore_unknown=True)   # reduce_batch: a node parameter
    env, ev = gym.make("CartPole-v1"), gym.make("CartPole-v1")
    lrn = ComperLearner(c, obs_shape=(4,), n_actions=2)
    assert lrn.network == "mlp"
    untrained = _greedy_return(lrn, ev)
    replay = ReplayBuffer(20_000, (4,), seed=0)
    obs, _ = env.reset(seed=0)
    for t in range(12_000):
        a, _ = lrn.act(obs.astype(np.float32), frames=t)
        nxt, r, term, trunc, _ = env.step(a)
        replay.add(Transitions(states=obs[None].astype(np.float32), actions=np.array([a], np.float32),
                               rewards=np.array([r], np.float32), next_states=nxt[None].astype(np.float32),
                               terminated=np.array([term]), truncated=np.array([trunc])))
        obs = env.reset()[0] if term or trunc else nxt
        if t >= c.learning_starts and t % c.train_frequency == 0:
            lrn.update(replay.sample(c.batch_size))
        if t % c.target_update_every == 0:
            lrn.sync_target()
    trained = _greedy_return(lrn, ev)
    assert trained >= max(50.0, 5 * untrained), (untrained, trained)      # seed 0: 13.2 -> 89.6
