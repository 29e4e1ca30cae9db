"""QT (comper_agent.core.qt): training, value units, batch independence, serialisation, L > 1."""
import json
import sys
from pathlib import Path
from types import SimpleNamespace

_SRC = Path(__file__).resolve().parents[2] / "src"
for _p in (_SRC / "comper_msgs", _SRC / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import numpy as np
import pytest
import torch

from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import config_from_dict
from comper_agent.core.config import ComcactQTConfig, QTConfig
from comper_agent.core.qt import (QTModel, default_key_fn, history_windows, newest_labels,
                                  reduction_predictor)

torch.set_num_threads(1)   # tiny models; the shared 2-core machine is often busy


def synthetic(m=256, d=8, seed=0, max_hist=4):
    rng = np.random.default_rng(seed)
    keys = (rng.normal(size=(m, d)) * 3 + 5).astype(np.float32)
    w = rng.normal(size=d).astype(np.float32)
    target = (10.0 * np.tanh((keys - 5) @ w / 6) + 100.0).astype(np.float32)
    lengths = rng.integers(1, max_hist + 1, size=m).astype(np.uint32)
    hist = []
    for i in range(m):
        hist.extend(list(rng.normal(100, 5, size=lengths[i] - 1)) + [target[i]])
    return keys, np.asarray(hist, np.float32), lengths, target


def cfg(**kw):
    return config_from_dict(QTConfig, {"qt_lr": 2e-3, **kw})


def test_fit_reduces_loss_and_predicts_in_value_units():
    keys, hist, lengths, target = synthetic()
    qt = QTModel(cfg(qt_batch_size=32, qt_lr=4e-3))
    first = qt.fit(keys, hist, lengths, epochs=1)
    for _ in range(5):
        last = qt.fit(keys, hist, lengths, epochs=4)
    assert last < 0.5 * first
    pred = qt.predict(keys)
    assert pred.dtype == np.float32 and pred.shape == (256,)
    mse = float(np.mean((pred - target) ** 2))
    assert mse < 0.3 * float(np.var(target))          # learned, in value units
    assert abs(float(pred.mean()) - float(target.mean())) < 2.0
    assert qt.version == 6 and qt.train_sets == 256


def test_predictions_are_batch_independent():
    keys, hist, lengths, _ = synthetic(m=64)
    qt = QTModel(cfg(), key_dim=keys.shape[1])
    qt.fit(keys, hist, lengths, epochs=2)
    full = qt.predict(keys)
    perm = np.random.default_rng(1).permutation(64)
    np.testing.assert_allclose(qt.predict(keys[perm]), full[perm], rtol=0, atol=1e-5)
    np.testing.assert_allclose(qt.predict(keys[:3]), full[:3], rtol=0, atol=1e-5)
    np.testing.assert_allclose(qt.predict(keys[5:6]), full[5:6], rtol=0, atol=1e-5)


@pytest.mark.parametrize("config_cls,seq", [(QTConfig, 1), (ComcactQTConfig, 1), (QTConfig, 3)])
def test_to_arrays_round_trip(config_cls, seq):
    keys, hist, lengths, _ = synthetic(m=48)
    qt = QTModel(config_from_dict(config_cls, {"qt_sequence_length": seq}))
    qt.fit(keys, hist, lengths, epochs=1)
    arrays = qt.to_arrays()
    json.dumps(arrays["config"])                      # travels as config_json
    assert all(v.dtype == np.float32 for v in arrays["tensors"].values())
    assert arrays["input_mean"].shape == (keys.shape[1],) and arrays["version"] == 1
    clone = QTModel.from_arrays(**arrays)
    np.testing.assert_array_equal(clone.predict(keys, hist, lengths), qt.predict(keys, hist, lengths))
    assert clone.config == qt.config and clone.version == 1


def test_comcact_architecture():
    qt = QTModel(ComcactQTConfig(), key_dim=5)
    assert [l.hidden_size for l in qt.net.lstms] == [64, 64]
    assert qt.net.dense.out_features == 32
    assert float(qt.net.out.weight.detach().abs().max()) <= 3e-4
    assert qt.net.output_activation == "linear"
    qt2 = QTModel(QTConfig(), key_dim=5)
    assert [l.hidden_size for l in qt2.net.lstms] == [64, 32, 32] and qt2.net.dense.out_features == 18
    assert isinstance(qt2.optimizer, torch.optim.RMSprop)
    g = qt2.optimizer.param_groups[0]
    assert (g["lr"], g["alpha"], g["eps"], g["momentum"]) == (2.5e-4, 0.9, 1e-10, 0.0)


def test_history_windows_left_pad():
    hist = np.array([1, 2, 3, 10, 20], np.float32)      # set 0: [1, 2, 3], set 1: [10], set 2: [20]
    lengths = np.array([3, 1, 1], np.uint32)
    labels, present = history_windows(hist, lengths, 3, exclude_newest=True)
    np.testing.assert_array_equal(labels, [[0, 1, 2], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(present, [[False, True, True], [False] * 3, [False] * 3])
    labels, present = history_windows(hist, lengths, 2, exclude_newest=False)
    np.testing.assert_array_equal(labels, [[2, 3], [0, 10], [0, 20]])
    np.testing.assert_array_equal(newest_labels(hist, lengths), [3, 10, 20])


def test_sequence_path_learns_from_history():
    # target = newest label = the previous label + 50: only the history can tell it
    rng = np.random.default_rng(0)
    m, L = 256, 3
    keys = rng.normal(size=(m, 4)).astype(np.float32)
    lengths = np.full(m, 3, np.uint32)
    prev = rng.uniform(0, 100, size=m).astype(np.float32)
    hist = np.stack([rng.uniform(0, 100, size=m), prev, prev + 50], axis=1).astype(np.float32).ravel()
    qt = QTModel(cfg(qt_sequence_length=L, qt_lr=3e-3))
    losses = [qt.fit(keys, hist, lengths, epochs=4) for _ in range(5)]
    assert losses[-1] < 0.1              # scaled units: 1.0 = predicting the mean
    # predict uses the whole history (newest included) to forecast the next label
    pred = qt.predict(keys, hist, lengths)
    assert pred.shape == (m,) and np.isfinite(pred).all()
    # without history the key-only (all padded) input still gives finite value-unit outputs
    assert np.isfinite(qt.predict(keys)).all()
    # single-label sets (all padding) are accepted for training
    qt.fit(keys[:4], hist[:4], np.ones(4, np.uint32))


def test_reduction_predictor_on_atari_like_lease():
    rng = np.random.default_rng(0)
    m = 40
    reps = Transitions(states=rng.integers(0, 256, size=(m, 84, 84), dtype=np.uint8),
                       actions=rng.integers(0, 18, size=m).astype(np.int64),
                       rewards=rng.normal(size=m).astype(np.float32),
                       next_states=rng.integers(0, 256, size=(m, 84, 84), dtype=np.uint8),
                       terminated=np.zeros(m, bool), truncated=np.zeros(m, bool))
    keys = default_key_fn(reps)
    assert keys.shape == (m, 14114) and keys.dtype == np.float32 and keys.max() <= 18
    lengths = rng.integers(1, 5, size=m).astype(np.uint32)
    hist = rng.normal(1, 0.1, size=int(lengths.sum())).astype(np.float32)
    lease = SimpleNamespace(representatives=reps, label_history=hist, history_lengths=lengths,
                            counts=lengths.copy())
    qt = QTModel(QTConfig())
    pred = reduction_predictor(qt, epochs=1)(lease)
    assert pred.shape == (m,) and pred.dtype == np.float32 and qt.version == 1
    assert abs(float(pred.mean()) - 1.0) < 0.5        # value units, not scaled units
    empty = SimpleNamespace(representatives=reps.take(slice(0, 0)), label_history=hist[:0],
                            history_lengths=lengths[:0], counts=lengths[:0])
    assert reduction_predictor(qt)(empty).shape == (0,)


def _atari_lease(m, frames, seed):
    rng = np.random.default_rng(seed)
    shape = (m, frames, 84, 84)
    reps = Transitions(states=rng.integers(0, 256, size=shape, dtype=np.uint8),
                       actions=rng.integers(0, 18, size=m).astype(np.int64),
                       rewards=np.sign(rng.normal(size=m)).astype(np.float32),
                       next_states=rng.integers(0, 256, size=shape, dtype=np.uint8),
                       terminated=np.zeros(m, bool), truncated=np.zeros(m, bool))
    lengths = rng.integers(1, 5, size=m).astype(np.uint32)
    hist = rng.normal(1, 0.5, size=int(lengths.sum())).astype(np.float32)
    return SimpleNamespace(representatives=reps, label_history=hist, history_lengths=lengths, counts=lengths.copy())


def test_kept_buffers_give_the_whole_input_paths_values_and_are_reused():
    """QT's round with kept buffers (keys written into one kept array, each mini-batch scaled when drawn,
    predictions scaled into a kept array) against the whole-input path it replaces: equal parameters and
    predictions bit for bit over three rounds of different sizes, and the buffers are mapped once."""
    kept, whole = QTModel(QTConfig(qt_batch_size=8)), QTModel(QTConfig(qt_batch_size=8))
    whole.kept_buffers = False
    for r, m in enumerate((37, 50, 20)):
        lease = _atari_lease(m, 2, r)
        got, ref = reduction_predictor(kept)(lease), reduction_predictor(whole)(lease)
        assert np.array_equal(got, ref), r
        assert all(torch.equal(a, b) for a, b in zip(kept.net.parameters(), whole.net.parameters()))
        assert np.array_equal(kept.input_mean, whole.input_mean) and np.array_equal(kept.input_std, whole.input_std)
    key_dim = 2 * 2 * 84 * 84 + 2
    assert kept.key_rows.nbytes == 50 * key_dim * 4 and kept._input_rows.nbytes == 50 * key_dim * 4
    assert whole.key_rows.nbytes == 0 and whole._input_rows.nbytes == 0
    keys = default_key_fn(_atari_lease(30, 2, 9).representatives)
    assert np.array_equal(kept.predict(keys), whole.predict(keys))
    # another caller while the buffer is held gets its own array (same values)
    with kept.key_rows.rows(10, 4) as a, kept.key_rows.rows(10, 4) as b:
        assert not np.shares_memory(a, b)


def test_rejects_bad_input():
    qt = QTModel(QTConfig(), key_dim=3)
    with pytest.raises(ValueError):
        qt.predict(np.zeros((2, 4), np.float32))
    with pytest.raises(ValueError):
        qt.fit(np.zeros((2, 3), np.float32), np.array([1.0, np.nan], np.float32), np.ones(2, np.uint32))


def test_native_lstm_equals_torch_lstm_with_the_same_parameters():
    """NativeLSTM (QT's LSTM, independent of the oneDNN flag) = nn.LSTM: outputs, states, gradients."""
    import torch
    from torch import nn

    from comper_agent.core.qt import NativeLSTM
    torch.manual_seed(3)
    ref = nn.LSTM(37, 8, batch_first=True)
    nat = NativeLSTM(37, 8, batch_first=True)
    nat.load_state_dict(ref.state_dict())                # same parameter names and shapes
    x = torch.randn(5, 4, 37)
    with torch.backends.mkldnn.flags(enabled=False):
        out_r, (h_r, c_r) = ref(x)
    out_n, (h_n, c_n) = nat(x)
    for a, b in ((out_r, out_n), (h_r, h_n), (c_r, c_n)):
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-6)
    (out_r ** 2).sum().backward()
    (out_n ** 2).sum().backward()
    for p, q in zip(ref.parameters(), nat.parameters()):
        assert torch.allclose(p.grad, q.grad, atol=1e-5)


def test_running_moments_row_by_row_equal_the_float64_copy_they_replace():
    """_Moments sums rows one by one instead of converting the whole batch to float64: the same values."""
    from comper_agent.core.qt import _Moments
    rng = np.random.default_rng(3)
    batches = [rng.integers(0, 256, size=(n, 300)).astype(np.float32) / 255.0 for n in (1, 17, 64)]
    m = _Moments(300)
    n, mean, m2 = 0, None, None
    for x in batches:
        m.update(x, refit=False)
        x64 = x.astype(np.float64)                     # the former computation, written out
        mb, m2b = x64.mean(axis=0), ((x64 - x64.mean(axis=0)) ** 2).sum(axis=0)
        if n == 0:
            n, mean, m2 = x.shape[0], mb, m2b
        else:
            tot = n + x.shape[0]
            delta = mb - mean
            mean, m2, n = mean + delta * (x.shape[0] / tot), m2 + m2b + delta ** 2 * (n * x.shape[0] / tot), tot
        assert m.n == n
        np.testing.assert_array_equal(m.mean, mean)
        np.testing.assert_array_equal(m.m2, m2)


@pytest.mark.parametrize("momentum", [0.0, 0.5])
def test_qt_rmsprop_steps_equal_torch_rmsprop(momentum):
    """QT's RMSprop keeps a sqrt buffer instead of allocating one per step: the same parameters after
    several steps as torch.optim.RMSprop, the same state_dict; with momentum it is torch's own step."""
    import copy
    from comper_agent.core.qt import _RMSprop
    torch.manual_seed(0)
    net = QTModel(QTConfig(), key_dim=40).net
    ref = copy.deepcopy(net)
    kw = dict(lr=2.5e-4, alpha=0.9, eps=1e-10, momentum=momentum)
    ours, theirs = _RMSprop(net.parameters(), **kw), torch.optim.RMSprop(ref.parameters(), **kw)
    for i in range(5):
        x, y = torch.randn(8, 1, 40), torch.randn(8)
        for model, opt in ((net, ours), (ref, theirs)):
            opt.zero_grad(set_to_none=True)
            torch.mean((model(x) - y) ** 2).backward()
            opt.step()
    for a, b in zip(net.parameters(), ref.parameters()):
        assert torch.equal(a, b)
    sa, sb = ours.state_dict(), theirs.state_dict()
    assert sa["state"].keys() == sb["state"].keys()
    for k in sa["state"]:
        assert sa["state"][k].keys() == sb["state"][k].keys()
        for name in sa["state"][k]:
            assert torch.equal(sa["state"][k][name], sb["state"][k][name]), name


def _training_data_and_twin_models(rng, m: int, key_dim: int):
    """m sets of random keys with one label each, and two QTModels with the same initial weights."""
    import copy
    keys = rng.random((m, key_dim)).astype(np.float32)
    hist = rng.normal(size=m).astype(np.float32)
    model = QTModel(QTConfig(), key_dim=key_dim)
    return keys, hist, np.ones(m, np.int64), model, copy.deepcopy(model)


def test_kept_input_weight_gradient_equals_autograds_and_reuses_its_memory():
    """A large LSTM input weight trained on inputs without gradient keeps its .grad tensor between
    backward passes (NativeLSTM.keep_grad_min_numel, lowered here): the same gradients and the same QT
    fit as autograd's fresh tensor, the same accumulation rules, and one buffer for every step."""
    from comper_agent.core.qt import NativeLSTM
    rng = np.random.default_rng(4)
    keys, hist, lengths, kept, ref = _training_data_and_twin_models(rng, 48, 300)
    lstm = kept.net.lstms[0]
    lstm.keep_grad_min_numel = 0                       # instance only; ref keeps the class threshold
    assert ref.net.lstms[0].weight_ih_l0.numel() < NativeLSTM.keep_grad_min_numel
    w = lstm.weight_ih_l0
    # one backward: the gradient lands in the kept buffer and equals autograd's
    x = torch.as_tensor(rng.random((16, 1, 300)), dtype=torch.float32)
    for net in (kept.net, ref.net):
        net.zero_grad(set_to_none=True)
        (net(x) ** 2).sum().backward()
    assert w.grad is lstm._weight_grad
    for a, b in zip(kept.net.parameters(), ref.net.parameters()):
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-6, atol=1e-7)
    # accumulation: a second backward adds, as autograd does
    for net in (kept.net, ref.net):
        (net(x) ** 2).sum().backward()
    torch.testing.assert_close(w.grad, ref.net.lstms[0].weight_ih_l0.grad, rtol=1e-6, atol=1e-7)
    # QT fits (zero_grad(set_to_none=True) each mini-batch): same parameters and predictions, one buffer
    buf = lstm._weight_grad
    for model in (kept, ref):
        model.fit(keys, hist, lengths)
        model.fit(keys[::-1].copy(), hist, lengths)
    assert lstm._weight_grad is buf and w.grad.data_ptr() == buf.data_ptr()
    for a, b in zip(kept.net.parameters(), ref.net.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(kept.predict(keys, hist, lengths), ref.predict(keys, hist, lengths), rtol=1e-5,
                               atol=1e-6)
    # inference and inputs that need a gradient take autograd's path
    with torch.no_grad():
        kept.net(x)
    xg = x.clone().requires_grad_(True)
    kept.net.zero_grad(set_to_none=True)
    (kept.net(xg) ** 2).sum().backward()
    assert xg.grad is not None and w.grad is not buf


def test_qt_compile_fuses_the_large_weights_update_to_the_eager_values():
    """qt_compile: the compiled RMSprop update of a large weight (threshold lowered here) gives the eager
    step's parameters up to float rounding, and says whether it compiled; off leaves no compiled part."""
    import copy
    from comper_agent.core.networks import cpp_compiler
    from comper_agent.core.qt import _RMSprop
    keys, hist, lengths, eager, fused = _training_data_and_twin_models(np.random.default_rng(6), 64, 200)
    fused.optimizer = _RMSprop(fused.net.parameters(), lr=2.5e-4, alpha=0.9, eps=1e-10, compile="default")
    fused.optimizer.fused_min_numel = 1000          # the first LSTM layer's 256 x 200 input weight
    for m in (eager, fused):
        m.fit(keys, hist, lengths)
        m.fit(keys, hist, lengths)
    for a, b in zip(fused.net.parameters(), eager.net.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    rep = fused.optimizer.compile_report()
    assert rep["mode"] == "default" and rep["compiled"] == (cpp_compiler() is not None), rep
    assert copy.deepcopy(fused).optimizer.compile_report()["mode"] == "default"   # a copy keeps the setting
    assert eager.optimizer.compile_report() == {} and QTConfig().qt_compile == "off"
