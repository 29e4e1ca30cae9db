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
    kw = {"actor_hidden": [32, 24], "critic_hidden": [32, 24], **kw}
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

    def _critic_step(self, s, a, y):
        self.critic.train()
        self._apply(((self.critic(s, a) - y) ** 2).mean(), self.critic, self.critic_opt)
        self.critic.eval()

    def step(self, b: Transitions, qt: np.ndarray) -> None:
        s, a, r, s2 = (torch.tensor(x) for x in (b.states, b.actions, b.rewards, b.next_states))
        live = torch.tensor(~b.terminated, dtype=torch.float32)
        with torch.no_grad():
            y = r + self.c.gamma * live * self.critic_target(s2, self.actor_target(s2))
        y_qt = r + self.c.gamma * live * torch.tensor(qt)
        self._critic_step(s, a, y)
        self.actor.train()
        self.critic.train()
        self._apply(-self.critic(s, self.actor(s)).mean(), self.actor, self.actor_opt)
        self.actor.eval()
        self.critic.eval()
        if self.c.variant == "comcact":
            self._critic_step(s, a, y_qt)
        with torch.no_grad():
            for tgt, src in ((self.actor_target, self.actor), (self.critic_target, self.critic)):
                for t, p in zip(tgt.state_dict().values(), src.state_dict().values()):
                    t.copy_(t + self.c.tau * (p - t) if t.dtype.is_floating_point else p)


def run(lrn: ComcactLearner, data) -> None:
    """The updates as comcact_node drives them (QT targets given, here fixed per batch)."""
    comcact = lrn.config.variant == "comcact"
    for b, qt in data:
        lrn.update(b)
        if comcact:
            lrn.qt_critic_step(b, qt)
        lrn.soft_update()


def assert_same(lrn, other, atol=1e-6, rtol=1e-5):
    for net in NETS:
        for (k, p), q in zip(getattr(lrn, net).state_dict().items(), getattr(other, net).state_dict().values()):
            torch.testing.assert_close(p, q, atol=atol, rtol=rtol, msg=lambda m: f"{net}.{k}: {m}")


@pytest.mark.parametrize("variant", ["ddpg", "comcact"])
@pytest.mark.parametrize("batch_norm,grad_clip,action_input", [(False, 0.0, "second_hidden"),
                                                               (True, 0.0, "second_hidden"), (False, 0.05, "output")])
def test_eager_step_equals_the_reference_parameter_by_parameter(variant, batch_norm, grad_clip, action_input):
    lrn = learner(variant=variant, batch_norm=batch_norm, grad_clip=grad_clip,
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


def test_a_qt_target_count_that_does_not_match_the_batch_is_refused_before_any_step():
    (b, qt), = batches(1)
    lrn = learner()
    with pytest.raises(ValueError, match="3 QT targets for 32 transitions"):
        lrn.qt_critic_step(b, qt[:3])
    assert lrn.qt_steps == 0
    with pytest.raises(RuntimeError, match="ddpg variant"):
        learner(variant="ddpg").qt_critic_step(b, qt)


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
    eager = learner()
    with pytest.warns(RuntimeWarning, match="no C.. compiler found"):
        lrn = learner(learner_compile="default")
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
    lrn = learner(learner_compile="default")
    ref = Reference(lrn)
    data = batches()
    run(lrn, data)
    for b, qt in data:
        ref.step(b, qt)
    rep = lrn.compile_report()
    assert all(r["compiled"] and r["compile_s"] > 0 for r in rep.values()), rep
    assert_same(lrn, ref, atol=1e-5, rtol=1e-4)    # compiled kernels round in another order
    assert lrn.update(data[0][0])["compile_s"] == pytest.approx(sum(r["compile_s"] for r in rep.values()))
