"""COMPER / DQN learner (comper_agent.core.comper)."""
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
from comper_agent.core.comper import ComperLearner, DQNRMSprop, linear_epsilon
from comper_agent.core.config import ComperConfig, DQNConfig
from comper_agent.core.networks import NatureCNN

torch.set_num_threads(1)   # tiny models; the shared 2-core machine is often busy


def frames_batch(n=8, channels=1, seed=0, terminated=None):
    rng = np.random.default_rng(seed)
    shape = (n, 84, 84) if channels == 1 else (n, channels, 84, 84)
    return Transitions(states=rng.integers(0, 256, size=shape, dtype=np.uint8),
                       actions=rng.integers(0, 18, size=n).astype(np.int64),
                       rewards=rng.normal(size=n).astype(np.float32),
                       next_states=rng.integers(0, 256, size=shape, dtype=np.uint8),
                       terminated=np.zeros(n, bool) if terminated is None else terminated,
                       truncated=np.zeros(n, bool))


def test_cnn_shapes_and_inputs():
    net = NatureCNN(1, 18)
    assert sum(p.numel() for p in net.parameters()) == 2080 + 32832 + 36928 + 1606144 + 9234
    x = torch.randint(0, 256, (2, 84, 84), dtype=torch.uint8)
    q = net(x)
    assert q.shape == (2, 18)
    torch.testing.assert_close(net(x.unsqueeze(1)), q)
    torch.testing.assert_close(net(x.float() / 255), q)        # uint8 scaled once, inside
    net4 = NatureCNN(4, 18)
    x4 = torch.randint(0, 256, (2, 4, 84, 84), dtype=torch.uint8)
    torch.testing.assert_close(net4(x4.permute(0, 2, 3, 1)), net4(x4))


def test_one_update_lowers_huber_loss_comper():
    lrn = ComperLearner(ComperConfig())
    b = frames_batch()
    qt = np.random.default_rng(1).normal(size=len(b)).astype(np.float32)
    before = lrn.loss(b, qt)
    m = lrn.update(b, qt)
    assert m["loss"] == pytest.approx(before, rel=1e-5)
    assert lrn.loss(b, qt) < before
    with pytest.raises(ValueError):
        lrn.update(b)                                        # comper needs QT targets


def test_dqn_variant_uses_target_network():
    lrn = ComperLearner(DQNConfig())
    assert lrn.q_target is not None and lrn.q.in_channels == 4
    b = frames_batch(channels=4, terminated=np.array([True] * 4 + [False] * 4))
    y = lrn.targets(b)
    np.testing.assert_allclose(y[:4].numpy(), b.rewards[:4], atol=1e-6)
    before = lrn.loss(b)
    lrn.update(b)
    assert lrn.loss(b) < before
    t0 = next(lrn.q_target.parameters()).clone()
    assert not torch.equal(t0, next(lrn.q.parameters()))
    lrn.sync_target()
    assert torch.equal(next(lrn.q_target.parameters()), next(lrn.q.parameters()))


def test_terminated_masks_qt_bootstrap_and_labels():
    lrn = ComperLearner(ComperConfig())
    term = np.array([True, False, True, False])
    b = frames_batch(4, terminated=term)
    b.truncated[:] = True                                       # truncation never masks
    qt = np.full(4, 2.0, np.float32)
    y = lrn.targets(b, qt).numpy()
    np.testing.assert_allclose(y, b.rewards + 0.99 * 2.0 * (~term), atol=1e-6)
    v = lrn.value_labels(b)
    assert v.dtype == np.float32 and np.all(v[term] == 0) and np.all(v[~term] != 0)
    with torch.no_grad():
        expected = lrn.q(torch.as_tensor(b.next_states)).max(1).values.numpy()
    np.testing.assert_allclose(v[~term], expected[~term], atol=1e-6)
    lrn_q = ComperLearner(config_from_dict(ComperConfig, {"qt_label": "q_sa"}))
    with torch.no_grad():
        q = lrn_q.q(torch.as_tensor(b.states)).numpy()
    np.testing.assert_allclose(lrn_q.value_labels(b), q[np.arange(4), b.actions], atol=1e-6)


def test_epsilon_schedule():
    c = ComperConfig()
    assert linear_epsilon(0) == 1.0
    assert linear_epsilon(45_000) == pytest.approx(0.505)
    assert linear_epsilon(90_000) == pytest.approx(0.01)
    assert linear_epsilon(10**7) == pytest.approx(0.01)
    lrn = ComperLearner(c)
    assert lrn.epsilon(0) == 1.0 and lrn.epsilon(90_000) == pytest.approx(0.01)
    obs = np.zeros((84, 84), np.uint8)
    a, q = lrn.act(obs, epsilon=0.0)
    assert a == int(np.argmax(q)) and q.shape == (18,)
    actions = {lrn.act(obs, frames=0)[0] for _ in range(60)}
    assert len(actions) > 8                                    # epsilon 1: uniform


def test_dqn_rmsprop_matches_formula():
    p = torch.nn.Parameter(torch.tensor([1.0, -2.0]))
    opt = DQNRMSprop([p], lr=0.1, grad_momentum=0.95, sq_grad_momentum=0.95, min_sq_grad=0.01)
    g = n = torch.zeros(2)
    expected = p.detach().clone()
    for grad in ([0.5, -1.0], [0.2, 0.3]):
        grad = torch.tensor(grad)
        p.grad = grad.clone()
        opt.step()
        g = 0.95 * g + 0.05 * grad
        n = 0.95 * n + 0.05 * grad ** 2
        expected = expected - 0.1 * grad / torch.sqrt(n - g ** 2 + 0.01)
    torch.testing.assert_close(p.detach(), expected)


@pytest.mark.parametrize("variant", ["comper", "comper_f"])
def test_learner_learns_a_state_dependent_greedy_policy(variant):
    """The CNN learner with Table 32's RMSProp turns its greedy action into a function of the frame within
    150 updates on a two-context bandit (one-step episodes; action 1 pays in context 0, action 2 in context
    1). The benchmark's 100,000-frame policies never moved off the initial network's constant action
    (docs/comper.md), so this shows the learner itself can."""
    best = np.array([1, 2])
    rng = np.random.default_rng(0)

    def frames(ctx):
        x = rng.integers(0, 40, size=(len(ctx), 84, 84), dtype=np.uint8)
        for i, c in enumerate(ctx):           # a bright square: bottom right in context 1, top left in 0
            if c:
                x[i, 50:80, 50:80] = 220
            else:
                x[i, 4:34, 4:34] = 220
        return x

    lrn = ComperLearner(config_from_dict(ComperConfig, {"variant": variant, "seed": 0}))
    probe = np.repeat([0, 1], 20)

    def greedy_right():
        with torch.no_grad():
            a = lrn.q(torch.as_tensor(frames(probe))).argmax(1).numpy()
        return float(np.mean(a == best[probe]))

    assert greedy_right() == 0.0                       # the initial network's argmax is another action
    for _ in range(150):
        ctx = rng.integers(0, 2, 32)
        a = np.where(rng.random(32) < 0.5, best[ctx], rng.integers(0, 18, 32))   # half on-policy, half random
        s = frames(ctx)
        lrn.update(Transitions(states=s, actions=a.astype(np.int64), rewards=(a == best[ctx]).astype(np.float32),
                               next_states=s, terminated=np.ones(32, bool), truncated=np.zeros(32, bool)),
                   np.zeros(32, np.float32) if variant == "comper" else None)
    assert greedy_right() == 1.0
