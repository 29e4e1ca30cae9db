"""COMPER / DQN learner (comper_agent.core.comper)."""
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
    np.testing.assert_allclose(y[:4].numpy(), np.clip(b.rewards[:4], -1, 1), atol=1e-6)   # reward_clip clip
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
    np.testing.assert_allclose(y, np.clip(b.rewards, -1, 1) + 0.99 * 2.0 * (~term), atol=1e-6)
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


def _reference_clipped_error_grads(q_net, batch, y):
    """DeepMind's gradient written out: sum over the batch of clip(Q(s_i, a_i) - y_i, -1, 1) dQ(s_i, a_i)/dtheta
    (error clipping = the Huber loss's derivative with delta 1), independent of the learner's loss code."""
    q_net.zero_grad(set_to_none=True)
    q = q_net(torch.as_tensor(batch.states))
    q_sa = q.gather(1, torch.as_tensor(batch.actions, dtype=torch.int64).reshape(-1, 1)).squeeze(1)
    err = (q_sa - y).clamp(-1.0, 1.0).detach()
    (err * q_sa).sum().backward()
    return [p.grad.detach().clone() for p in q_net.parameters()]


@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_two_updates_equal_deepmind_rmsprop_on_the_summed_clipped_errors(reduction):
    """Parameter by parameter: two learner updates (dqn-style target network, single frames, unclipped
    and large rewards) equal a reference computation of DeepMind's RMSProp on the sum over the batch of
    the clipped TD errors, rewards clipped to [-1, 1]: g and n momenta 0.95, p -= lr grad / sqrt(n - g^2 +
    0.01). loss_reduction mean (with its rescaled constant) must give the same step as sum."""
    import copy
    cfg = config_from_dict(ComperConfig, {"variant": "comper_f", "seed": 3, "loss_reduction": reduction})
    lrn = ComperLearner(cfg)
    ref = copy.deepcopy(lrn.q)
    ref.train(False)
    ref_target = copy.deepcopy(lrn.q_target)
    params = list(ref.parameters())
    g = [torch.zeros_like(p) for p in params]
    n = [torch.zeros_like(p) for p in params]
    for k in range(2):
        b = frames_batch(16, seed=10 + k)
        b.rewards[:4] = [50.0, -7.0, 0.5, 0.0]             # clipped: 1, -1, 0.5, 0
        b.terminated[-3:] = True
        with torch.no_grad():
            boot = ref_target(torch.as_tensor(b.next_states)).max(1).values
            y = (torch.as_tensor(np.clip(b.rewards, -1, 1)) + 0.99 * boot
                 * (1.0 - torch.as_tensor(b.terminated, dtype=torch.float32)))
        grads = _reference_clipped_error_grads(ref, b, y)
        with torch.no_grad():
            for p, gi, ni, grad in zip(params, g, n, grads):
                gi.mul_(0.95).add_(0.05 * grad)
                ni.mul_(0.95).add_(0.05 * grad * grad)
                p.sub_(2.5e-4 * grad / torch.sqrt(ni - gi * gi + 0.01))
        lrn.update(b)
        for (name, p), r in zip(lrn.q.named_parameters(), params):
            torch.testing.assert_close(p.detach(), r.detach(), rtol=1e-5, atol=2e-7, msg=f"{name} after update {k + 1}")
    moved = sum(float((p.detach() - q.detach()).abs().max()) for p, q in zip(lrn.q.parameters(),
                                                                          copy.deepcopy(lrn.q_target).parameters()))
    assert moved > 1e-4                                  # the comparison is not between two unmoved networks


def test_reward_clip_modes_shape_the_target_and_nothing_else():
    b = frames_batch(4, terminated=np.ones(4, bool))
    b.rewards[:] = [50.0, -3.0, 0.5, 0.0]
    want = {"clip": [1.0, -1.0, 0.5, 0.0], "sign": [1.0, -1.0, 1.0, 0.0], "none": [50.0, -3.0, 0.5, 0.0]}
    for mode, expected in want.items():
        lrn = ComperLearner(config_from_dict(ComperConfig, {"reward_clip": mode}))
        y = lrn.targets(b, np.full(4, 5.0, np.float32)).numpy()
        np.testing.assert_allclose(y, expected, atol=1e-6)          # terminated: no bootstrap
    assert ComperConfig().reward_clip == "clip" and ComperConfig().loss_reduction == "sum"
    assert b.rewards[0] == 50.0                                      # the batch keeps the raw reward


def test_double_dqn_bootstraps_the_target_network_at_the_online_argmax():
    lrn = ComperLearner(config_from_dict(ComperConfig, {"variant": "comper_f", "double_dqn": True, "seed": 1}))
    with torch.no_grad():
        for p in lrn.q_target.parameters():
            p.add_(0.05 * torch.randn_like(p))
    b = frames_batch(6)
    ns = torch.as_tensor(b.next_states)
    with torch.no_grad():
        a_star = lrn.q(ns).argmax(1)
        boot = lrn.q_target(ns)[torch.arange(6), a_star]
    y = lrn.targets(b).numpy()
    np.testing.assert_allclose(y, np.clip(b.rewards, -1, 1) + 0.99 * boot.numpy(), rtol=1e-5, atol=1e-6)


def test_mlp_q_network_for_vector_observations_and_bad_shapes():
    from comper_agent.core.comper import resolve_q_network
    from comper_agent.core.networks import QMLP
    lrn = ComperLearner(config_from_dict(ComperConfig, {"variant": "dqn"}), obs_shape=(4,), n_actions=2)
    assert isinstance(lrn.q, QMLP) and lrn.network == "mlp"
    a, q = lrn.act(np.zeros(4, np.float32), epsilon=0.0)
    assert q.shape == (2,) and a in (0, 1)
    assert resolve_q_network("auto", (84, 84)) == "nature_cnn" and resolve_q_network("auto", (4, 84, 84)) == "nature_cnn"
    with pytest.raises(ValueError, match="1-D observations"):
        resolve_q_network("mlp", (84, 84))
    with pytest.raises(ValueError, match="84x84"):
        resolve_q_network("nature_cnn", (6,))
    with pytest.raises(ValueError, match="neither a vector nor frames"):
        resolve_q_network("auto", (2, 3, 4, 5))


def test_profiles_name_existing_fields_with_a_source_and_auto_follows_the_task():
    from dataclasses import fields
    from comper_agent.core.config import COMPER_PROFILES, resolve_profile
    from comper_agent.nodes.node_config import ComperNodeConfig
    owner = {**{f.name: ComperNodeConfig for f in fields(ComperNodeConfig)},
             **{f.name: ComperConfig for f in fields(ComperConfig)}}   # a learner or a node parameter
    for profile, values in COMPER_PROFILES.items():
        for k, (v, source) in values.items():
            assert k in owner, (profile, k)
            assert isinstance(source, str) and len(source) > 10, (profile, k)
            config_from_dict(owner[k], {k: v})                       # a valid value
    assert resolve_profile("auto", "ALE/Freeway-v5") == "atari_100k"
    assert resolve_profile("auto", "CartPole-v1") == "classic_control"
    assert resolve_profile("data_efficient", "ALE/Asterix-v5") == "data_efficient"


def test_qt_diagnostics_measure_qt_against_the_networks_own_bootstrap():
    """ComperLearner.qt_diagnostics on a fixed batch against a reference computed here: QT equal to
    max_a Q(s', a) has no error; QT and the stored labels shifted by 1 are off by gamma on every live row;
    the TD error is the loss's own; the action statistics are those of argmax Q; nothing moves."""
    lrn = ComperLearner(config_from_dict(ComperConfig, {"q_network": "mlp"}), obs_shape=(3,), n_actions=4)
    rng = np.random.default_rng(3)
    n = 64
    term = np.zeros(n, bool)
    term[:16] = True
    b = Transitions(states=rng.normal(size=(n, 3)).astype(np.float32), actions=rng.integers(0, 4, n),
                    rewards=(3 * rng.normal(size=n)).astype(np.float32),
                    next_states=rng.normal(size=(n, 3)).astype(np.float32), terminated=term,
                    truncated=np.zeros(n, bool))
    with torch.no_grad():
        v = lrn.q(torch.as_tensor(b.next_states)).max(1).values.numpy() * ~term
        q = lrn.q(torch.as_tensor(b.states)).numpy()
    b.value_labels = (v + 1.0).astype(np.float32)
    exact = lrn.qt_diagnostics(b, v)
    assert exact["qt_target_rmse"] == pytest.approx(0.0, abs=1e-6) and exact["qt_bias"] == pytest.approx(0.0, abs=1e-6)
    y = np.clip(b.rewards, -1, 1) + 0.99 * ~term * v                    # reward_clip sign, as the loss
    q_sa = q[np.arange(n), b.actions]
    assert exact["td_rmse"] == pytest.approx(float(np.sqrt(np.mean((q_sa - y) ** 2))), rel=1e-5)
    assert exact["label_bias"] == pytest.approx(1.0, rel=1e-5)          # live rows only
    assert exact["q_gap_mean"] == pytest.approx(float((q.max(1) - q.min(1)).mean()), rel=1e-5)
    greedy = q.argmax(1)
    assert exact["greedy_top_share"] == pytest.approx(np.bincount(greedy).max() / n)
    live = v[~term]
    assert exact["v_next_mean"] == pytest.approx(float(live.mean()), rel=1e-5)
    assert exact["v_next_std"] == pytest.approx(float(live.std()), rel=1e-4)
    assert exact["qt_v_corr"] == pytest.approx(1.0, abs=1e-5)
    off = lrn.qt_diagnostics(b, v + 1.0)
    assert off["qt_target_rmse"] == pytest.approx(0.99 * np.sqrt(48 / 64), rel=1e-5)
    assert off["qt_bias"] == pytest.approx(1.0, rel=1e-5)
    assert off["qt_v_corr"] == pytest.approx(1.0, abs=1e-5)       # a shift keeps the correlation
    noise = rng.normal(size=n).astype(np.float32)
    ref = np.corrcoef(noise[~term], live)[0, 1]
    assert lrn.qt_diagnostics(b, noise)["qt_v_corr"] == pytest.approx(ref, abs=1e-5)
    assert np.isnan(lrn.qt_diagnostics(b, np.full(n, 2.0, np.float32))["qt_v_corr"])   # QT flat: undefined
    b.value_labels = np.zeros(0, np.float32)
    assert np.isnan(lrn.qt_diagnostics(b, v)["label_bias"])
    before = copy.deepcopy(lrn.q.state_dict())
    lrn.qt_diagnostics(b, v)
    assert all(torch.equal(before[k], p) for k, p in lrn.q.state_dict().items())


def vector_batch(n: int, terminated_first: int, seed: int) -> Transitions:
    """n transitions of 3-d vector states and 4 actions, the first `terminated_first` terminated."""
    rng = np.random.default_rng(seed)
    term = np.zeros(n, bool)
    term[:terminated_first] = True
    return Transitions(states=rng.normal(size=(n, 3)).astype(np.float32), actions=rng.integers(0, 4, n),
                       rewards=rng.normal(size=n).astype(np.float32),
                       next_states=rng.normal(size=(n, 3)).astype(np.float32), terminated=term,
                       truncated=np.zeros(n, bool))


def test_the_per_step_label_is_the_max_of_the_q_values_computed_to_act():
    online = ComperLearner(config_from_dict(ComperConfig, {"q_network": "mlp"}), obs_shape=(3,), n_actions=4)
    assert online.q_target is None
    assert online.next_value(np.zeros(3, np.float32), np.array([1.0, 3.0, 2.0, 0.0])) == 3.0


def _check_gate(lrn, b, close, far, spread, boot):
    """QT = reference + 2 x spread (`far`) is gated with error 2 x spread and takes the target network's bootstrap
    `boot`; QT = reference + 0.5 x spread (`close`) keeps its own targets."""
    r, term = np.clip(b.rewards, -1, 1), b.terminated
    g = lrn.qt_gate(b, far)
    assert g["gated"] and g["error"] == pytest.approx(2.0 * spread, rel=1e-4)
    assert g["spread"] == pytest.approx(float(spread), rel=1e-4)
    assert not lrn.qt_gate(b, close)["gated"]
    np.testing.assert_allclose(lrn.targets(b, close).numpy(), r + 0.99 * ~term * close, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(lrn.targets(b, far).numpy(), r + 0.99 * ~term * boot, rtol=1e-5, atol=1e-6)


def test_qt_target_gate_takes_the_target_networks_bootstrap_only_where_qt_is_off_by_more_than_its_spread():
    """qt_target_gate (comper): per batch, error = RMS(QT(tau) - V(s')) and spread = std(V(s')) over the
    non-terminal rows, V(s') = max_a Q(s', a) the labels' bootstrap, B the target network's bootstrap, both computed
    here by hand; error > spread: the targets are comper_f's, r + gamma (1 - terminated) B(s'); otherwise QT's.
    Counted, reported, checkpointed; off by default (no target network), and comper_f has nothing to gate."""
    assert ComperLearner(config_from_dict(ComperConfig, {"q_network": "mlp"}), obs_shape=(3,), n_actions=4
                         ).q_target is None
    for double in (True, False):
        lrn = ComperLearner(config_from_dict(ComperConfig, {"q_network": "mlp", "qt_target_gate": True,
                                                            "double_dqn": double}), obs_shape=(3,), n_actions=4)
        assert lrn.uses_target_net and lrn.gates_qt and not lrn.bootstraps_from_target
        n = 32
        b = vector_batch(n, 4, seed=7)
        term = b.terminated
        for _ in range(10):                    # the online network moves away from its copy
            lrn.update(b, np.zeros(n, np.float32))
        with torch.no_grad():
            ns = torch.as_tensor(b.next_states)
            q_on, q_tg = lrn.q(ns).numpy(), lrn.q_target(ns).numpy()
        boot = q_tg[np.arange(n), q_on.argmax(1)] if double else q_tg.max(1)
        v = q_on.max(1)
        spread = v[~term].std()
        assert spread > 0
        r = np.clip(b.rewards, -1, 1)
        close = v + 0.5 * spread                  # error 0.5 x spread: QT's targets stay
        far = v + 2.0 * spread                    # error 2 x spread: the target network's
        _check_gate(lrn, b, close, far, spread, boot)
        diag = lrn.qt_diagnostics(b, far)
        assert diag["qt_gate_on"] == 1.0 and diag["qt_gate_spread"] == pytest.approx(float(spread), rel=1e-4)
        # the diagnostics compare QT itself with V(s') (the labels' network), and the TD error is against the
        # target the loss sees (here the target network's)
        with torch.no_grad():
            q_sa = lrn.q(torch.as_tensor(b.states)).numpy()[np.arange(n), b.actions]
        qt_rmse = np.sqrt(np.mean((0.99 * ~term * (far - v * ~term)) ** 2))
        assert diag["qt_target_rmse"] == pytest.approx(float(qt_rmse), rel=1e-4)
        td = np.sqrt(np.mean((q_sa - (r + 0.99 * ~term * boot)) ** 2))
        assert diag["td_rmse"] == pytest.approx(float(td), rel=1e-4)
        open_diag = lrn.qt_diagnostics(b, close)
        assert open_diag["qt_gate_on"] == 0.0
        td = np.sqrt(np.mean((q_sa - (r + 0.99 * ~term * close)) ** 2))
        assert open_diag["td_rmse"] == pytest.approx(float(td), rel=1e-4)
        before = lrn.qt_gated, lrn.updates
        assert lrn.update(b, far)["qt_gated"] == 1.0
        assert lrn.update(b, close)["qt_gated"] == 0.0
        assert lrn.qt_gated == before[0] + 1 and lrn.updates == before[1] + 2
        ended = Transitions(states=b.states, actions=b.actions, rewards=b.rewards, next_states=b.next_states,
                            terminated=np.ones(n, bool), truncated=b.truncated)
        assert not lrn.qt_gate(ended, far)["gated"]          # no bootstrap to compare
        restored = ComperLearner(lrn.config, obs_shape=(3,), n_actions=4)
        restored.load_state_dict(lrn.state_dict())
        assert restored.qt_gated == lrn.qt_gated
    plain = ComperLearner(config_from_dict(ComperConfig, {"q_network": "mlp"}), obs_shape=(3,), n_actions=4)
    assert "qt_gated" not in plain.update(b, far) and "qt_gate_on" not in plain.qt_diagnostics(b, far)
    f = ComperLearner(config_from_dict(ComperConfig, {"q_network": "mlp", "variant": "comper_f",
                                                      "qt_target_gate": True}), obs_shape=(3,), n_actions=4)
    assert not f.gates_qt and "qt_gated" not in f.update(b)
