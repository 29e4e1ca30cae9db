"""The COMCACT / DDPG learner step against a reference computation of it, eager and compiled
(comper_agent.core.comcact, learner_compile; docs/agent-core.md "Learner step speed")."""
import copy
import dataclasses
import sys
import warnings
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
from comper_agent.core import networks
from comper_agent.core.comcact import ComcactLearner
from comper_agent.core.config import ComcactConfig

torch.set_num_threads(1)
OBS, ACT = 6, 2
LOW, HIGH = np.array([-2.0, -1.0], np.float32), np.array([2.0, 1.0], np.float32)
NETS = ("actor", "critic", "actor_target", "critic_target")


def batches(n=3, size=32):
    rng = np.random.default_rng(7)
    return [(Transitions(states=rng.normal(size=(size, OBS)).astype(np.float32),
                         actions=rng.uniform(LOW, HIGH, size=(size, ACT)).astype(np.float32),
                         rewards=rng.normal(size=size).astype(np.float32),
                         next_states=rng.normal(size=(size, OBS)).astype(np.float32),
                         terminated=np.arange(size) % 5 == 0, truncated=np.zeros(size, bool)),
             rng.normal(size=size).astype(np.float32)) for _ in range(n)]


def learner(**kw):
    kw = {"actor_hidden": [32, 24], "critic_hidden": [32, 24], "qt_step_weight": 0.5, **kw}
    return ComcactLearner(config_from_dict(ComcactConfig, kw), OBS, LOW, HIGH)


class Reference:
    """The update written out from its definition on copies of a learner's networks: separate Adam
    optimisers (same settings), each step's gradient accumulated by backward() into exactly the
    parameters it changes."""

    def __init__(self, lrn: ComcactLearner):
        c = self.c = lrn.config
        for net in NETS:
            setattr(self, net, copy.deepcopy(getattr(lrn, net)))
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=c.actor_lr, fused=True)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=c.critic_lr, fused=True)

    def _apply(self, loss, net, opt):
        params = list(net.parameters())
        loss.backward(inputs=params)
        if self.c.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, self.c.grad_clip)
        opt.step()
        opt.zero_grad()

    def _heads(self, s, a):
        return (self.critic.q1(s, a), self.critic.q2(s, a)) if self.c.critic == "twin" else (self.critic(s, a),)

    def _critic_loss(self, s, a, y):
        return sum(((q - y) ** 2).mean() for q in self._heads(s, a))

    def _critic_step(self, s, a, y, weight=1.0, y_qt=None):
        """weight x the loss against y; with y_qt (qt_step_mode joint) the loss against y + qt_step_weight x
        the loss against y_qt, in the one step."""
        self.critic.train()
        loss = self._critic_loss(s, a, y) * weight
        if y_qt is not None:
            loss = loss + self.c.qt_step_weight * self._critic_loss(s, a, y_qt)
        self._apply(loss, self.critic, self.critic_opt)
        self.critic.eval()

    def step(self, b: Transitions, qt: np.ndarray) -> None:
        s, a, r, s2 = (torch.tensor(x) for x in (b.states, b.actions, b.rewards, b.next_states))
        live = torch.tensor(~b.terminated, dtype=torch.float32)
        with torch.no_grad():
            a2 = self.actor_target(s2)
            q2 = self.critic_target(s2, a2) if self.c.critic == "single" else torch.minimum(
                self.critic_target.q1(s2, a2), self.critic_target.q2(s2, a2))
            y = r + self.c.gamma * live * q2
        y_qt = r + self.c.gamma * live * torch.tensor(qt)
        joint = self.c.variant == "comcact" and self.c.qt_step_mode == "joint"
        self._critic_step(s, a, y, y_qt=y_qt if joint else None)
        self.actor.train()
        self.critic.train()
        self._apply(-self.critic(s, self.actor(s)).mean(), self.actor, self.actor_opt)
        self.actor.eval()
        self.critic.eval()
        if self.c.variant == "comcact" and not joint:
            self._critic_step(s, a, y_qt, self.c.qt_step_weight)
        with torch.no_grad():
            for tgt, src in ((self.actor_target, self.actor), (self.critic_target, self.critic)):
                for t, p in zip(tgt.state_dict().values(), src.state_dict().values()):
                    t.copy_(t + self.c.tau * (p - t) if t.dtype.is_floating_point else p)


def run(lrn: ComcactLearner, data) -> None:
    """The updates as comcact_node drives them (QT targets given, here fixed per batch)."""
    comcact = lrn.config.variant == "comcact"
    joint = comcact and lrn.config.qt_step_mode == "joint"
    for b, qt in data:
        lrn.update(b, qt if joint else None)
        if comcact and not joint:
            lrn.qt_critic_step(b, qt)
        lrn.soft_update()


def assert_same(lrn, other, atol=1e-6, rtol=1e-5):
    for net in NETS:
        for (k, p), q in zip(getattr(lrn, net).state_dict().items(), getattr(other, net).state_dict().values()):
            torch.testing.assert_close(p, q, atol=atol, rtol=rtol, msg=lambda m: f"{net}.{k}: {m}")


@pytest.mark.parametrize("variant", ["ddpg", "comcact"])
@pytest.mark.parametrize("critic", ["single", "twin"])
@pytest.mark.parametrize("batch_norm,grad_clip,action_input", [(False, 0.0, "second_hidden"),
                                                               (True, 0.0, "second_hidden"), (False, 0.05, "output")])
def test_eager_step_equals_the_reference_parameter_by_parameter(variant, critic, batch_norm, grad_clip, action_input):
    lrn = learner(variant=variant, critic=critic, batch_norm=batch_norm, grad_clip=grad_clip,
                  critic_action_input=action_input)
    ref = Reference(lrn)
    data = batches()
    run(lrn, data)
    for b, qt in data:
        ref.step(b, qt)
    assert lrn.updates == 3 and lrn.qt_steps == (3 if variant == "comcact" else 0)
    assert_same(lrn, ref)
    # the actor step leaves no gradient on the critic's weights and keeps them trainable
    assert all(p.requires_grad for p in lrn.critic.parameters())
    assert lrn.compile_report() == {}


@pytest.mark.parametrize("critic", ["single", "twin"])
@pytest.mark.parametrize("weight", [0.5, 1.0])
def test_joint_qt_step_is_one_critic_step_on_both_losses_equal_to_the_reference(critic, weight):
    """qt_step_mode joint: one Adam step of the critic on the DDPG loss + qt_step_weight x the QT loss, then
    the actor step; it differs from the thesis's two critic steps on the same data."""
    lrn = learner(critic=critic, qt_step_mode="joint", qt_step_weight=weight)
    separate = learner(critic=critic, qt_step_weight=weight)
    ref = Reference(lrn)
    data = batches()
    run(lrn, data)
    run(separate, data)
    for b, qt in data:
        ref.step(b, qt)
    assert lrn.updates == 3 and lrn.qt_steps == 3
    assert_same(lrn, ref)
    assert int(lrn.critic_opt.state_dict()["state"][0]["step"]) == 3      # one Adam step per update
    assert int(separate.critic_opt.state_dict()["state"][0]["step"]) == 6
    with pytest.raises(AssertionError):
        assert_same(lrn, separate)


def test_the_qt_targets_go_where_the_mode_takes_them():
    (b, qt), = batches(1)
    with pytest.raises(RuntimeError, match="joint only"):
        learner().update(b, qt)
    joint = learner(qt_step_mode="joint")
    with pytest.raises(RuntimeError, match="no separate QT step"):
        joint.qt_critic_step(b, qt)
    with pytest.raises(ValueError, match="3 QT targets for 32 transitions"):
        joint.update(b, qt[:3])
    assert joint.updates == 0 and joint.qt_steps == 0                     # refused before any step
    with pytest.raises(RuntimeError, match="ddpg variant"):
        learner(variant="ddpg", qt_step_mode="joint").update(b, qt)


def test_joint_mode_gate_drops_the_qt_term_and_leaves_the_ddpg_step():
    """qt_step_gate with joint: a batch whose QT target is far from the DDPG target takes the DDPG update
    alone (the same parameters as a DDPG learner's), one close to it takes the joint step."""
    (b, _), = batches(1)
    gated, ddpg = learner(qt_step_mode="joint", qt_step_gate=True), learner(variant="ddpg")
    y = gated.td_targets(b).numpy()
    live = ~b.terminated
    far = np.where(live, (y - b.rewards) / 0.99 + 100.0, 0.0).astype(np.float32)
    out = gated.update(b, far)
    ddpg.update(b)
    assert out["qt_gated"] == 1.0 and "qt_critic_loss" not in out and gated.qt_gated == 1 and gated.qt_steps == 0
    assert_same(gated, ddpg, atol=0.0, rtol=0.0)
    taken = learner(qt_step_mode="joint", qt_step_gate=True)
    close = np.where(live, (y - b.rewards) / 0.99, 0.0).astype(np.float32)   # QT = the DDPG bootstrap
    out = taken.update(b, close)
    assert out["qt_gated"] == 0.0 and taken.qt_steps == 1 and out["qt_critic_loss"] > 0.0


def test_qt_diagnostics_after_an_update_reuse_its_ddpg_targets_with_the_same_result():
    lrn = learner()
    (b, qt), (other, _) = batches(2)
    lrn.update(b)
    fresh = copy.deepcopy(lrn)
    fresh.soft_update(0.0)                          # forgets the update's targets; a lerp by 0 moves nothing
    assert_same(lrn, fresh, atol=0.0, rtol=0.0)
    assert lrn.qt_diagnostics(b, qt) == fresh.qt_diagnostics(b, qt)
    assert lrn.qt_diagnostics(other, qt) == fresh.qt_diagnostics(other, qt)   # another batch: its own targets
    with torch.no_grad():
        lrn.critic_target.out.bias += 1.0            # Q' + 1 everywhere
    lrn.soft_update(0.0)                            # after a target update the targets are computed again
    assert lrn.qt_diagnostics(b, qt)["qt_bias"] == pytest.approx(fresh.qt_diagnostics(b, qt)["qt_bias"] - 1.0,
                                                                 abs=1e-4)


def test_bad_compile_mode_is_refused_and_the_config_offers_exactly_the_modes():
    with pytest.raises(ValueError, match="compile mode must be one of"):
        networks.compile_or_eager(lambda x: x, "max-autotune", "f")
    field = {f.name: f for f in dataclasses.fields(ComcactConfig)}["learner_compile"]
    assert tuple(field.metadata["choices"]) == networks.COMPILE_MODES


def test_without_a_cpp_compiler_the_step_runs_eagerly_with_one_warning(monkeypatch):
    monkeypatch.setattr(networks, "cpp_compiler", lambda: None)
    eager = learner(critic="twin")
    with pytest.warns(RuntimeWarning, match="no C.. compiler found"):
        lrn = learner(critic="twin", learner_compile="default")
    data = batches()
    run(eager, data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run(lrn, data)
    assert_same(lrn, eager, atol=0.0, rtol=0.0)
    assert lrn.update(data[0][0])["compile_s"] == 0.0 and "compile_s" not in eager.update(data[0][0])
    rep = lrn.compile_report()
    assert set(rep) == {"targets", "critic_loss", "actor_loss"}
    assert all(not r["compiled"] and "no C++ compiler" in r["fallback"] for r in rep.values())


def test_a_compile_failure_on_the_first_call_falls_back_to_eager(monkeypatch):
    def broken_compile(fn, **kw):
        def compiled(*args):
            raise RuntimeError("backend failed\nlong traceback")
        return compiled
    monkeypatch.setattr(networks, "cpp_compiler", lambda: "g++")
    monkeypatch.setattr(torch, "compile", broken_compile)
    eager, lrn = learner(), learner(learner_compile="default")
    data = batches()
    run(eager, data)
    with pytest.warns(RuntimeWarning, match="running it eagerly: RuntimeError: backend failed$"):
        run(lrn, data)
    assert_same(lrn, eager, atol=0.0, rtol=0.0)
    assert all(r["fallback"] == "RuntimeError: backend failed" for r in lrn.compile_report().values())


@pytest.mark.slow
@pytest.mark.skipif(networks.cpp_compiler() is None, reason="torch.compile needs a C++ compiler on CPU")
def test_compiled_step_equals_the_reference():
    lrn = learner(critic="twin", learner_compile="default")
    ref = Reference(lrn)
    data = batches()
    run(lrn, data)
    for b, qt in data:
        ref.step(b, qt)
    rep = lrn.compile_report()
    assert all(r["compiled"] and r["compile_s"] > 0 for r in rep.values()), rep
    assert_same(lrn, ref, atol=1e-5, rtol=1e-4)    # compiled kernels round in another order
    assert lrn.update(data[0][0])["compile_s"] == pytest.approx(sum(r["compile_s"] for r in rep.values()))
