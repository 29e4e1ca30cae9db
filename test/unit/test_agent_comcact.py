"""COMCACT / DDPG learner, OU noise, replay buffer (comper_agent.core)."""
import copy
import sys
from pathlib import Path

_SRC = Path(__file__).resolve().parents[2] / "src"
for _p in (_SRC / "comper_msgs", _SRC / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import numpy as np
import pytest
import torch

from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import config_from_dict
from comper_agent.core.comcact import ComcactLearner
from comper_agent.core.config import ComcactConfig, DDPGConfig
from comper_agent.core.noise import OUNoise
from comper_agent.core.replay import ReplayBuffer

torch.set_num_threads(1)   # tiny models; the shared 2-core machine is often busy
OBS, ACT = 5, 2
LOW, HIGH = np.array([-2.0, -1.0]), np.array([2.0, 1.0])


def batch(n=64, seed=0, terminated=None, truncated=None):
    rng = np.random.default_rng(seed)
    return Transitions(
        states=rng.normal(size=(n, OBS)).astype(np.float32),
        actions=rng.uniform(LOW, HIGH, size=(n, ACT)).astype(np.float32),
        rewards=rng.normal(size=n).astype(np.float32),
        next_states=rng.normal(size=(n, OBS)).astype(np.float32),
        terminated=np.zeros(n, bool) if terminated is None else terminated,
        truncated=np.zeros(n, bool) if truncated is None else truncated)


def learner(cls=ComcactConfig, **kw):
    return ComcactLearner(config_from_dict(cls, kw), OBS, LOW, HIGH)


def train_mode_q(lrn, b, actor=None):
    s = torch.as_tensor(b.states)
    a = torch.as_tensor(b.actions) if actor is None else None
    with torch.no_grad():
        lrn.critic.train()
        if actor is not None:
            actor.train()
            a = actor(s)
        q = lrn.critic(s, a)
        lrn.critic.eval()
        if actor is not None:
            actor.eval()
    return q


def test_ddpg_update_lowers_td_loss_and_improves_actor():
    lrn = learner()
    b = batch()
    y = lrn.td_targets(b)
    loss_before = float(torch.mean((train_mode_q(lrn, b) - y) ** 2))
    actor_before = copy.deepcopy(lrn.actor)
    m = lrn.update(b)
    assert m["critic_loss"] == pytest.approx(loss_before, rel=1e-4)
    loss_after = float(torch.mean((train_mode_q(lrn, b) - y) ** 2))
    assert loss_after < loss_before
    # the actor step moved mu towards higher Q under the (updated) critic
    q_old = train_mode_q(lrn, b, actor_before).mean()
    q_new = train_mode_q(lrn, b, lrn.actor).mean()
    assert q_new > q_old
    assert lrn.updates == 1 and not lrn.actor.training and not lrn.critic.training


def test_qt_critic_step_moves_q_towards_qt_target():
    lrn = learner()
    b = batch(seed=1)
    qt = np.full(len(b), 5.0, np.float32)
    y = torch.as_tensor(b.rewards) + 0.99 * torch.as_tensor(qt)
    before = float(torch.mean(torch.abs(train_mode_q(lrn, b) - y)))
    m = lrn.qt_critic_step(b, qt)
    after = float(torch.mean(torch.abs(train_mode_q(lrn, b) - y)))
    assert after < before and lrn.qt_steps == 1
    assert m["qt_target_mean"] == pytest.approx(float(y.mean()), rel=1e-5)
    with pytest.raises(RuntimeError):
        learner(DDPGConfig).qt_critic_step(b, qt)


def test_terminated_masks_bootstrap_truncated_does_not():
    lrn = learner()
    n = 8
    term = batch(n, seed=2, terminated=np.ones(n, bool))
    trunc = batch(n, seed=2, truncated=np.ones(n, bool))
    np.testing.assert_allclose(lrn.td_targets(term).numpy(), term.rewards, atol=1e-6)
    boot = lrn.td_targets(trunc).numpy() - trunc.rewards
    assert np.all(np.abs(boot) > 0)
    np.testing.assert_array_equal(lrn.value_labels(term), np.zeros(n, np.float32))
    assert np.all(lrn.value_labels(trunc) != 0)
    qt = np.full(n, 3.0, np.float32)
    assert lrn.qt_critic_step(term, qt)["qt_target_mean"] == pytest.approx(float(term.rewards.mean()), abs=1e-5)
    assert lrn.qt_critic_step(trunc, qt)["qt_target_mean"] == pytest.approx(
        float(trunc.rewards.mean() + 0.99 * 3.0), abs=1e-5)


def test_value_labels_q_sa_and_batch_independence():
    b = batch(16, seed=3)
    lrn = learner(qt_label="q_sa")
    np.testing.assert_allclose(lrn.value_labels(b), lrn.q_values(b.states, b.actions), atol=1e-6)
    lrn = learner()
    full = lrn.value_labels(b)
    np.testing.assert_allclose(lrn.value_labels(b.take(slice(0, 3))), full[:3], atol=1e-6)


def test_act_bounds_noise_and_soft_update():
    lrn = learner()
    obs = np.random.default_rng(0).normal(size=OBS).astype(np.float32)
    greedy = lrn.act(obs, explore=False)
    assert greedy.shape == (ACT,) and np.all(greedy >= LOW) and np.all(greedy <= HIGH)
    np.testing.assert_array_equal(greedy, lrn.act(obs, explore=False))
    noisy = np.stack([lrn.act(obs, explore=True) for _ in range(50)])
    assert np.all(noisy >= LOW) and np.all(noisy <= HIGH) and noisy.std(axis=0).min() > 0
    assert lrn.act(np.stack([obs, obs]), explore=False).shape == (2, ACT)
    lrn.update(batch())
    p, pt = next(lrn.critic.parameters()), next(lrn.critic_target.parameters())
    gap = float((p - pt).detach().abs().sum())
    lrn.soft_update()
    assert float((p - pt).detach().abs().sum()) == pytest.approx(gap * (1 - 0.005), rel=1e-3)


def test_architecture_matches_appendix_b():
    lrn = learner()
    lin = [m for m in lrn.actor.modules() if isinstance(m, torch.nn.Linear)]
    assert [l.out_features for l in lin] == [400, 300, ACT]
    assert float(lin[-1].weight.detach().abs().max()) <= 3e-3
    assert float(lrn.critic.out.weight.detach().abs().max()) <= 3e-4
    assert lrn.critic.fc2.in_features == 400 + ACT
    assert learner(critic_action_input="output").critic.out.in_features == 300 + ACT
    assert lrn.actor_opt.param_groups[0]["lr"] == 1e-3 and lrn.critic_opt.param_groups[0]["lr"] == 2e-3
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in lrn.actor.modules())   # default: plain MLPs
    assert sum(isinstance(m, torch.nn.BatchNorm1d) for m in learner(batch_norm=True).actor.modules()) == 3
    plain = learner(batch_norm=False)
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in [*plain.actor.modules(), *plain.critic.modules()])
    assert [l.out_features for l in plain.actor.modules() if isinstance(l, torch.nn.Linear)] == [400, 300, ACT]


def test_ou_noise_statistics_reset_and_seed():
    noise = OUNoise(3, theta=0.15, sigma=0.2, dt=1.0, seed=0)
    xs = np.stack([noise.sample() for _ in range(20000)])
    assert xs.shape == (20000, 3) and xs.dtype == np.float32
    assert np.all(np.abs(xs[1000:].mean(axis=0)) < 0.08)
    np.testing.assert_allclose(xs[1000:].std(axis=0), noise.stationary_std(), rtol=0.1)
    # temporally correlated: lag-1 autocorrelation = 1 - theta dt
    x = xs[1000:, 0] - xs[1000:, 0].mean()
    assert np.corrcoef(x[:-1], x[1:])[0, 1] == pytest.approx(0.85, abs=0.03)
    noise.reset()
    np.testing.assert_array_equal(noise.state, np.zeros(3))
    a, b = OUNoise(2, seed=7), OUNoise(2, seed=7)
    np.testing.assert_array_equal([a.sample() for _ in range(5)], [b.sample() for _ in range(5)])


def test_replay_buffer_fifo_and_uniform_sampling():
    buf = ReplayBuffer(10, (OBS,), (ACT,), seed=0)
    b = batch(7)
    buf.add(b)
    assert len(buf) == 7
    buf.add(batch(7, seed=1))
    assert len(buf) == 10 and buf.pos == 4
    # the 4 oldest were overwritten by the last 4 of the second batch
    np.testing.assert_array_equal(buf.states[:4], batch(7, seed=1).states[3:])
    s = buf.sample(64)
    assert len(s) == 64 and s.actions.shape == (64, ACT) and s.terminated.dtype == bool
    s.validate()


def test_qt_diagnostics_measure_the_qt_target_against_the_ddpg_target():
    """qt_diagnostics on a fixed batch against a reference computed here: QT equal to Q'(s', mu'(s'))
    has no error; QT shifted by 1 is off by gamma on every non-terminal row (0 on terminal ones)."""
    lrn = learner()
    term = np.zeros(64, bool)
    term[:16] = True
    b = batch(terminated=term)
    s2 = torch.as_tensor(b.next_states)
    with torch.no_grad():
        q2 = lrn.critic_target(s2, lrn.actor_target(s2)).numpy()
        q = lrn.critic(torch.as_tensor(b.states), torch.as_tensor(b.actions)).numpy()
    y = b.rewards + 0.99 * (1 - term) * q2
    exact = lrn.qt_diagnostics(b, q2)
    assert exact["qt_target_rmse"] == pytest.approx(0.0, abs=1e-6) and exact["qt_bias"] == pytest.approx(0.0, abs=1e-6)
    assert exact["critic_td_rmse"] == pytest.approx(float(np.sqrt(np.mean((q - y) ** 2))), rel=1e-5)
    off = lrn.qt_diagnostics(b, q2 + 1.0)
    assert off["qt_target_rmse"] == pytest.approx(0.99 * np.sqrt(48 / 64), rel=1e-5)
    assert off["qt_bias"] == pytest.approx(1.0, rel=1e-5)
    before = copy.deepcopy(lrn.critic.state_dict())
    lrn.qt_diagnostics(b, q2)                       # measures only: no parameter moves
    assert all(torch.equal(before[k], v) for k, v in lrn.critic.state_dict().items())


def _qt_step_change(gate=False, shift=0.0):
    """Parameter change of one QT step after one shared DDPG step (the Adam state both steps share)."""
    lrn = learner(qt_step_gate=gate)
    b = batch(seed=3)
    lrn.update(b)
    s2 = torch.as_tensor(b.next_states)
    with torch.no_grad():
        q2 = lrn.critic_target(s2, lrn.actor_target(s2)).numpy()
    before = torch.cat([p.detach().flatten().clone() for p in lrn.critic.parameters()])
    out = lrn.qt_critic_step(b, q2 + shift)
    after = torch.cat([p.detach().flatten() for p in lrn.critic.parameters()])
    return float((after - before).norm()), out, lrn


def test_qt_step_gate_skips_a_qt_target_worse_than_the_critic_s_own():
    close, out, _ = _qt_step_change(gate=True, shift=0.0)      # QT = the DDPG target: the step is taken
    assert close > 0.0 and out["qt_gated"] == 0.0
    far, out, lrn = _qt_step_change(gate=True, shift=100.0)    # far off: skipped, nothing moves
    assert far == 0.0 and out["qt_gated"] == 1.0 and lrn.qt_gated == 1 and lrn.qt_steps == 0


def test_qt_step_gate_decides_on_qt_diagnostics_figures():
    """The gate's test is qt_diagnostics' on the same batch before the step: gated exactly where
    qt_target_rmse > critic_td_rmse, for shifts of the QT target on both sides of the critic's TD error."""
    seen = set()
    for shift in (0.0, 0.05, 0.2, 0.5, 1.0, 3.0):
        lrn = learner(qt_step_gate=True)
        b = batch(seed=3)
        lrn.update(b)
        s2 = torch.as_tensor(b.next_states)
        with torch.no_grad():
            qt = lrn.critic_target(s2, lrn.actor_target(s2)).numpy() + shift
        d = lrn.qt_diagnostics(b, qt)
        out = lrn.qt_critic_step(b, qt)
        assert out["qt_gated"] == float(d["qt_target_rmse"] > d["critic_td_rmse"])
        seen.add(out["qt_gated"])
    assert seen == {0.0, 1.0}


def test_label_critic_target_labels_with_the_target_networks():
    """label_critic target: the label is Q'(s', mu'(s')) (0 when terminated), the DDPG target's own
    bootstrap; online (the thesis): Q(s', mu(s')). They differ once an update has moved the online nets."""
    term = np.zeros(16, bool)
    term[:4] = True
    b = batch(16, seed=5, terminated=term)
    online, target = learner(seed=2), learner(seed=2, label_critic="target")
    for lrn in (online, target):
        lrn.update(batch(seed=6))
    s2 = torch.as_tensor(b.next_states)
    with torch.no_grad():
        ref = target.critic_target(s2, target.actor_target(s2)).numpy() * ~term
    np.testing.assert_allclose(target.value_labels(b), ref, atol=1e-6)
    np.testing.assert_allclose(target.value_labels(b), (target.td_targets(b).numpy() - b.rewards) / 0.99, atol=1e-4)
    assert np.all(target.value_labels(b)[:4] == 0.0)
    assert np.abs(online.value_labels(b) - target.value_labels(b))[4:].max() > 1e-4


def test_actor_step_moves_the_actor_alone():
    lrn = learner()
    b = batch(seed=7)
    critic_before = [p.detach().clone() for p in lrn.critic.parameters()]
    actor_before = [p.detach().clone() for p in lrn.actor.parameters()]
    out = lrn.actor_step(b.states)
    assert set(out) == {"actor_loss", "actor_saturation"} and lrn.updates == 0
    assert all(torch.equal(p, q) for p, q in zip(lrn.critic.parameters(), critic_before))
    assert any(not torch.equal(p, q) for p, q in zip(lrn.actor.parameters(), actor_before))
    assert not lrn.actor.training and not lrn.critic.training
