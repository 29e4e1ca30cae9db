"""QT, the Q-target network (method.md section 3; thesis Table 37 and appendix B).

QT maps a similar-transition set's representative key (and, with ``qt_sequence_length`` L > 1,
the set's recent value labels) to a prediction of the set's next value label.

Size: the network, its training and prediction, scaling, and the array form the QTModel message
carries are one model's parts; the long docstrings state the input layout they must agree on.

Inputs and targets
------------------
* keys [M, key_dim] float32, built by a ``key_fn`` from the representative transitions (default
  :func:`default_key_fn`, which is ``comper_memory.core.transition_keys``: the memory's own keys).
* label histories are flat float32 arrays (all sets' histories concatenated, oldest first) plus
  ``history_lengths`` [M] (the layout of ``comper_msgs/ReductionSets``).
* :meth:`QTModel.fit` trains on (input built from everything *before* each set's newest label,
  target = the newest label). :meth:`QTModel.predict` builds the input from the *whole* given
  history (so it forecasts the label that would come next); with no history it sees the key only.
* L = 1: the input is the scaled key as a length-1 sequence; histories are used for targets only.
* L > 1: the input is a length-L sequence; step j is [scaled key, scaled label_j, 1]. Sets with
  fewer than L earlier labels are left-padded with steps [scaled key, 0, 0] (the presence flag 0
  tells the LSTM the label is missing; 0 is the label mean in scaled units). A set whose only
  label is the target therefore trains on a sequence of L padded steps, i.e. on its key alone.

Scaling
-------
Inputs are standardised per feature and targets to zero mean and unit variance with a scaler that
lives in the model (and travels with its weights). ``qt_scaler = running`` accumulates the moments
over all training rounds; ``refit`` replaces them each round. Features with std < 1e-6 (constant
pixels) get std 1. Predictions are converted back to value units.

Batch independence
------------------
The network has no batch-dependent layers and predicts in eval mode, so a set's prediction does
not depend on which other sets share the batch (up to float rounding of batched matmuls).
"""
from __future__ import annotations

import contextlib
import threading
from typing import Callable

import numpy as np
import torch
from torch import nn

from comper_memory.core.keys import key_size_of, transition_keys
from comper_msgs_py.params import config_to_dict

from .config import QTConfig, qt_config_for
from .networks import compile_or_eager

__all__ = ["QTNetwork", "QTModel", "default_key_fn", "reduction_predictor", "history_windows",
           "newest_labels", "QT_FORMAT_VERSION"]

#: the key of each transition: the memory's own key builder (concat(s, a, r, s'), frames scaled by 1/255)
default_key_fn = transition_keys

QT_FORMAT_VERSION = 1
_STD_FLOOR = 1e-6


def _offsets(history_lengths: np.ndarray) -> np.ndarray:
    lengths = np.asarray(history_lengths, dtype=np.int64)
    return np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)


def newest_labels(label_history: np.ndarray, history_lengths: np.ndarray) -> np.ndarray:
    """The last label of each set's history, float32 [M]."""
    lengths = np.asarray(history_lengths, dtype=np.int64)
    if np.any(lengths < 1):
        raise ValueError("every set needs a history of at least one label")
    return np.asarray(label_history, dtype=np.float32)[_offsets(lengths) + lengths - 1]


def history_windows(label_history: np.ndarray, history_lengths: np.ndarray, length: int,
                    *, exclude_newest: bool) -> tuple[np.ndarray, np.ndarray]:
    """The last `length` labels of each set (before the newest if `exclude_newest`), left-padded.

    Returns (labels [M, length] float32, present [M, length] bool); padded slots hold 0 / False.
    Vectorised, no per-set Python loop.
    """
    hist = np.asarray(label_history, dtype=np.float32)
    lengths = np.asarray(history_lengths, dtype=np.int64)
    m = lengths.shape[0]
    if length == 0 or m == 0:
        return np.zeros((m, length), np.float32), np.zeros((m, length), bool)
    start = _offsets(lengths)
    end = start + lengths - (1 if exclude_newest else 0)      # exclusive
    idx = end[:, None] - length + np.arange(length)[None, :]
    present = idx >= start[:, None]
    labels = np.where(present, hist[np.clip(idx, 0, max(hist.size - 1, 0))] if hist.size else 0.0, 0.0)
    return labels.astype(np.float32), present


class _RowBuffer:
    """A kept float32 [rows, dim] scratch array, grown to the most rows asked for and reused: QT's round
    builds 3,300 sets of 4-frame keys (745 MB) and their scaled inputs each time, and on a machine whose free
    memory is page cache, fresh pages of that size cost seconds to map (the kernel reclaims cache for them).
    ``rows(n, dim)`` is a context manager giving a C-contiguous [n, dim] view; while one caller holds it, another
    gets a new array (correct, just not reused)."""

    def __init__(self):
        self._a: np.ndarray | None = None
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def rows(self, n: int, dim: int):
        if not self._lock.acquire(blocking=False):
            yield np.empty((n, dim), np.float32)
            return
        try:
            a = self._a
            if a is None or a.shape[1] != dim or a.shape[0] < n:
                self._a = a = None                  # let the old one go before the new one is mapped
                a = self._a = np.empty((n, dim), np.float32)
            yield a[:n]
        finally:
            self._lock.release()

    @property
    def nbytes(self) -> int:
        return 0 if self._a is None else int(self._a.nbytes)

    def __getstate__(self):          # scratch space: a copy (deepcopy, pickle) starts empty
        return {}

    def __setstate__(self, state):
        self.__init__()


def _kept_like(buf: torch.Tensor | None, t: torch.Tensor) -> torch.Tensor:
    """`buf` when it can hold a tensor like `t` (shape, dtype, device), else a new empty one: the scratch
    tensors QT keeps between steps instead of allocating them per step."""
    if buf is not None and buf.shape == t.shape and buf.dtype == t.dtype and buf.device == t.device:
        return buf
    return torch.empty_like(t)


class _KeptWeightGrad(torch.autograd.Function):
    """Identity on the input projection gx = x W^T + b whose weight was detached; its backward writes
    dL/dW = grad^T x into the module's kept buffer (``out=``) and makes it W's .grad, instead of letting
    autograd allocate a new tensor per backward. For QT's first layer on 4-frame Atari keys W is 58 MB:
    the fresh allocation (above glibc's 32 MB mmap ceiling, so never reused) page-faulted ~14,000 pages
    per mini-batch, about 3/4 of the backward pass's time. Accumulates like autograd: into an existing
    .grad (zero_grad(set_to_none=False), or two backward calls), else into the buffer. For .backward()
    only: torch.autograd.grad does not see W."""

    @staticmethod
    def forward(ctx, gx, x, lstm):
        ctx.save_for_backward(x)
        ctx.lstm = lstm
        return gx.view_as(gx)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        lstm = ctx.lstm
        w = lstm.weight_ih_l0
        g2, x2 = grad.reshape(-1, grad.shape[-1]).t(), x.reshape(-1, x.shape[-1])
        if w.grad is not None:
            w.grad.addmm_(g2, x2)
        else:
            buf = lstm._weight_grad = _kept_like(lstm._weight_grad, w)
            w.grad = torch.mm(g2, x2, out=buf)
        return grad, None, None


class NativeLSTM(nn.LSTM):
    """nn.LSTM (one layer, unidirectional, batch_first; same parameters and state_dict) computed
    with plain matrix products: the input projection of all steps in one product, then the L
    recurrent steps. Why: torch routes nn.LSTM to oneDNN's RNN kernel whenever the process-wide
    oneDNN flag is on (the Nature CNN wants it on), and that kernel is slower here; this path does
    not depend on the flag, so QT can train on one thread while the CNN learns on another
    (reduce_overlap). Measured (1 thread, forward + backward, idle 2-core machine): COMPER's
    14114-input LSTM, batch 16, L 5: 29 ms against nn.LSTM's 40 ms (oneDNN on) / 30 ms (off);
    COMCACT-size (14 -> 64, batch 64, L 1): 2.6x faster than nn.LSTM with oneDNN on; for L 10 at
    this size nn.LSTM's fused loop is faster (~2x). Other configurations fall back to nn.LSTM.
    Same result as nn.LSTM up to float32 rounding (tested).

    An input weight of at least ``keep_grad_min_numel`` elements keeps its gradient's memory between
    backward passes (_KeptWeightGrad) when it is trained on inputs that need no gradient."""

    keep_grad_min_numel = 1 << 22       # 16 MB of float32; smaller blocks are reused by the allocator

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._weight_grad: torch.Tensor | None = None

    def forward(self, x, hx=None):
        if (self.num_layers != 1 or self.bidirectional or self.proj_size or not self.batch_first
                or not isinstance(x, torch.Tensor) or x.dim() != 3):
            return super().forward(x, hx)
        b, steps, _ = x.shape
        bias = self.bias_ih_l0 + self.bias_hh_l0 if self.bias else None
        w = self.weight_ih_l0
        if (w.requires_grad and torch.is_grad_enabled() and not x.requires_grad
                and w.numel() >= self.keep_grad_min_numel):
            gx = _KeptWeightGrad.apply(nn.functional.linear(x, w.detach(), bias), x, self)
        else:
            gx = nn.functional.linear(x, w, bias)                          # [B, L, 4H]
        if hx is None:
            h = x.new_zeros(b, self.hidden_size)
            c = x.new_zeros(b, self.hidden_size)
        else:
            h, c = hx[0][0], hx[1][0]
        outs = []
        for t in range(steps):                                          # gate order i, f, g, o
            i, f, g, o = (gx[:, t] + nn.functional.linear(h, self.weight_hh_l0)).chunk(4, 1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
            outs.append(h)
        return torch.stack(outs, 1), (h.unsqueeze(0), c.unsqueeze(0))


class QTNetwork(nn.Module):
    """Stacked LSTMs (tanh) -> Dense ReLU -> Dense 1 (linear or tanh).

    Input [B, L, in_dim]; the last LSTM's final output feeds the dense layers. Output [B].
    """

    def __init__(self, in_dim: int, lstm_units: list[int], dense_units: int,
                 output_activation: str = "linear", output_init: float = 0.0):
        super().__init__()
        sizes = [in_dim] + list(lstm_units)
        self.lstms = nn.ModuleList(NativeLSTM(sizes[i], sizes[i + 1], batch_first=True)
                                   for i in range(len(lstm_units)))
        self.dense = nn.Linear(sizes[-1], dense_units)
        self.out = nn.Linear(dense_units, 1)
        if output_init > 0:
            nn.init.uniform_(self.out.weight, -output_init, output_init)
            nn.init.zeros_(self.out.bias)
        self.output_activation = output_activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for lstm in self.lstms:
            x, _ = lstm(x)
        h = torch.relu(self.dense(x[:, -1]))
        y = self.out(h).squeeze(-1)
        return torch.tanh(y) if self.output_activation == "tanh" else y


class _Moments:
    """Running mean / variance (Chan et al. parallel update), float64."""

    def __init__(self, dim: int):
        self.n = 0
        self.mean = np.zeros(dim, np.float64)
        self.m2 = np.zeros(dim, np.float64)

    def update(self, x: np.ndarray, refit: bool) -> None:
        x = np.asarray(x)
        x = x.reshape(x.shape[0], -1)
        nb = x.shape[0]
        if nb == 0:
            return
        mb, m2b = self.batch_moments(x)
        if refit or self.n == 0:
            self.n, self.mean, self.m2 = nb, mb, m2b
            return
        n = self.n + nb
        delta = mb - self.mean
        self.mean = self.mean + delta * (nb / n)
        self.m2 = self.m2 + m2b + delta ** 2 * (self.n * nb / n)
        self.n = n

    @staticmethod
    def batch_moments(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and summed squared deviations of the rows of x [nb, dim], float64. The sums are taken row by
        row, the order of x.astype(float64).mean(axis=0) and of its squared deviations (the same values,
        tested), without that [nb, dim] float64 copy and its temporaries: 1,784 sets of 4-frame Atari keys
        are 800 MB each, and building them took 5 s of a 20 s QT round."""
        total = x[0].astype(np.float64)
        for row in x[1:]:
            total += row
        mb = total / x.shape[0]
        m2b = np.square(x[0] - mb)
        for row in x[1:]:
            m2b += np.square(row - mb)
        return mb, m2b

    def std(self) -> np.ndarray:
        std = np.sqrt(self.m2 / max(self.n, 1))
        return np.where(std < _STD_FLOOR, 1.0, std)


def _rms_update(p: torch.Tensor, grad: torch.Tensor, sq: torch.Tensor, lr: float, alpha: float, eps: float,
                denom: torch.Tensor | None = None) -> None:
    """One plain RMSprop step in place, torch's order of operations. The eager step passes `denom`, a kept
    tensor for sqrt(square average) + eps; under torch.compile (no `denom`) the passes fuse into one."""
    sq.mul_(alpha).addcmul_(grad, grad, value=1 - alpha)
    denom = torch.sqrt(sq) if denom is None else torch.sqrt(sq, out=denom)
    p.addcdiv_(grad, denom.add_(eps), value=-lr)


class _RMSprop(torch.optim.RMSprop):
    """torch.optim.RMSprop whose plain step (no momentum, not centred: QT's Table 33 setting) writes sqrt(square
    average) into a buffer kept per parameter instead of a new tensor per step: the same operations in the same
    order (equal parameters, tested), without re-allocating (and page-faulting) QT's first-layer weights' size
    at every mini-batch, 58 MB for 4-frame Atari keys. Other settings take torch's own step. The buffers are
    scratch space, not optimiser state: state_dict is torch's."""

    fused_min_numel = 1 << 22           # with compile != off: the weights the compiled update takes

    def __init__(self, params, compile: str = "off", **kw):
        super().__init__(params, **kw)
        self.defaults["qt_compile"] = compile        # kept by copy.deepcopy / pickle with torch's state
        self._scratch()

    def _scratch(self) -> None:
        self._sqrt_buf: dict[torch.Tensor, torch.Tensor] = {}
        mode = self.defaults.get("qt_compile", "off")
        self._fused = compile_or_eager(_rms_update, mode, "QT's RMSprop update") if mode != "off" else None

    def __setstate__(self, state):      # copy.deepcopy / pickle keep torch's state only: new scratch space
        super().__setstate__(state)
        self._scratch()

    def compile_report(self) -> dict:
        """{} when qt_compile is off, else CompiledOrEager.report() (compiled, compile_s, fallback)."""
        return self._fused.report() if self._fused is not None else {}

    @torch.no_grad()
    def step(self, closure=None):
        if closure is not None or any(g["momentum"] or g["centered"] or g["weight_decay"] or g["maximize"]
                                      or g.get("capturable") or g.get("differentiable")
                                      for g in self.param_groups):
            return super().step(closure)
        for g in self.param_groups:
            lr, alpha, eps = g["lr"], g["alpha"], g["eps"]
            for p in g["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["step"] = torch.zeros((), dtype=torch.get_default_dtype())
                    st["square_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                st["step"] += 1
                sq = st["square_avg"]
                if self._fused is not None and p.numel() >= self.fused_min_numel:
                    self._fused(p, p.grad, sq, lr, alpha, eps)
                else:
                    buf = self._sqrt_buf[p] = _kept_like(self._sqrt_buf.get(p), p)
                    _rms_update(p, p.grad, sq, lr, alpha, eps, buf)
        return None


class QTModel:
    """QT with its scaler and optimiser; numpy in, numpy out.

    ``key_dim`` may be None: the network is then built on the first fit/predict.
    """

    #: L = 1: fit scales each mini-batch's inputs when it is drawn, predict scales into a kept buffer, and
    #: reduction_predictor builds the keys into one (equal values, tested). False: the whole scaled input is
    #: built at once and each round's arrays are new (the earlier way; qt_fit_bench.py's baseline)
    kept_buffers = True

    def __init__(self, config: QTConfig | None = None, key_dim: int | None = None):
        self.config = config or QTConfig()
        self.device = torch.device(self.config.qt_device)
        self.key_dim: int | None = None
        self.net: QTNetwork | None = None
        self.optimizer: torch.optim.Optimizer | None = None
        self.version = 0                 # training rounds so far; 0 = untrained
        self.train_loss = float("nan")   # mean loss of the last round (scaled units)
        self.train_sets = 0
        self._gen = torch.Generator().manual_seed(self.config.qt_seed + 1)
        self.key_rows = _RowBuffer()     # reduction_predictor's keys
        self._input_rows = _RowBuffer()  # predict's scaled inputs (L = 1, CPU)
        if key_dim is not None:
            self._build(int(key_dim))

    # ---------------------------------------------------------------- construction
    @property
    def sequence_length(self) -> int:
        return int(self.config.qt_sequence_length)

    @property
    def in_dim(self) -> int:
        assert self.key_dim is not None
        return self.key_dim + (2 if self.sequence_length > 1 else 0)

    def _build(self, key_dim: int) -> None:
        c = self.config
        self.key_dim = key_dim
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(c.qt_seed)
            self.net = QTNetwork(self.in_dim, list(c.qt_lstm_units), c.qt_dense_units,
                                 c.qt_output_activation, c.qt_output_init).to(self.device)
        self.net.eval()
        self.optimizer = _RMSprop(self.net.parameters(), lr=c.qt_lr, alpha=c.qt_rms_alpha,
                                  eps=c.qt_rms_eps, momentum=c.qt_rms_momentum, compile=c.qt_compile)
        self._in = _Moments(key_dim)
        self._lab = _Moments(1)
        self.input_mean = np.zeros(key_dim, np.float32)
        self.input_std = np.ones(key_dim, np.float32)
        self.label_mean = 0.0
        self.label_std = 1.0

    def _ensure(self, keys: np.ndarray) -> None:
        if keys.ndim != 2:
            raise ValueError(f"keys must be [M, key_dim], got shape {keys.shape}")
        if self.net is None:
            self._build(keys.shape[1])
        elif keys.shape[1] != self.key_dim:
            raise ValueError(f"keys have {keys.shape[1]} features, QT expects {self.key_dim}")

    # ---------------------------------------------------------------- inputs
    def _inputs(self, keys: np.ndarray, label_history, history_lengths, *, exclude_newest: bool
                ) -> torch.Tensor:
        """Scaled input sequences [M, L, in_dim] on the model's device."""
        k = self._scaled(torch.from_numpy(np.ascontiguousarray(keys, dtype=np.float32)))
        L = self.sequence_length
        if L == 1:
            return k.unsqueeze(1)
        m = keys.shape[0]
        if label_history is None or history_lengths is None:
            labels = np.zeros((m, L), np.float32)
            present = np.zeros((m, L), bool)
        else:
            labels, present = history_windows(label_history, history_lengths, L,
                                              exclude_newest=exclude_newest)
            labels = np.where(present, (labels - self.label_mean) / self.label_std, 0.0)
        lab = torch.from_numpy(labels.astype(np.float32)).to(self.device)
        pres = torch.from_numpy(present.astype(np.float32)).to(self.device)
        return torch.cat([k.unsqueeze(1).expand(m, L, self.key_dim), lab.unsqueeze(-1),
                          pres.unsqueeze(-1)], dim=-1)

    def _scaled(self, k: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """(k - input_mean) / input_std on the model's device, as a new tensor or into ``out`` (k is left as it
        is): one write, the division in place, the same values as the two-step expression."""
        k = k.to(self.device)
        x = torch.sub(k, torch.from_numpy(self.input_mean).to(self.device), out=out)
        return x.div_(torch.from_numpy(self.input_std).to(self.device))

    def _update_scaler(self, keys: np.ndarray, targets: np.ndarray) -> None:
        refit = self.config.qt_scaler == "refit"
        self._in.update(keys, refit)
        self._lab.update(targets.reshape(-1, 1), refit)
        self.input_mean = self._in.mean.astype(np.float32)
        self.input_std = self._in.std().astype(np.float32)
        self.label_mean = float(self._lab.mean[0])
        self.label_std = float(self._lab.std()[0])

    # ---------------------------------------------------------------- training / prediction
    def fit(self, keys: np.ndarray, label_history: np.ndarray, history_lengths: np.ndarray,
            epochs: int | None = None, batch_size: int | None = None) -> float:
        """Train on M sets (target: each set's newest label). Returns the mean loss (MSE in scaled
        units) over the mini-batches of the last epoch."""
        keys = np.asarray(keys, dtype=np.float32)
        self._ensure(keys)
        m = keys.shape[0]
        if m == 0:
            return float("nan")
        lengths = np.asarray(history_lengths, dtype=np.int64)
        if lengths.shape != (m,):
            raise ValueError(f"history_lengths must have shape ({m},), got {lengths.shape}")
        targets = newest_labels(label_history, lengths)
        if not (all(np.isfinite(keys[i:i + 256]).all() for i in range(0, m, 256)) and np.isfinite(targets).all()):
            raise ValueError("QT training data holds NaN or Inf")
        self._update_scaler(keys, targets)
        if self.sequence_length == 1 and self.kept_buffers:
            # each mini-batch's inputs are scaled when it is drawn (the same values as rows of the whole scaled
            # input, which for 3,300 sets of 4-frame keys is 745 MB written afresh at every round)
            raw = torch.from_numpy(keys)
            x = None
        else:
            x = self._inputs(keys, label_history, lengths, exclude_newest=True)
        y = torch.from_numpy((targets - self.label_mean) / self.label_std).float().to(self.device)
        epochs = int(epochs or self.config.qt_epochs)
        bs = int(batch_size or self.config.qt_batch_size)
        net, opt = self.net, self.optimizer
        assert net is not None and opt is not None
        net.train()
        losses: list[torch.Tensor] = []
        for _ in range(epochs):
            losses = []
            perm = torch.randperm(m, generator=self._gen).to(self.device)
            for i in range(0, m, bs):
                idx = perm[i:i + bs]
                xb = self._scaled(raw[idx.cpu()]).unsqueeze(1) if x is None else x[idx]
                loss = torch.mean((net(xb) - y[idx]) ** 2)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                if self.config.qt_grad_clip > 0:
                    nn.utils.clip_grad_norm_(net.parameters(), self.config.qt_grad_clip)
                opt.step()
                losses.append(loss.detach())
        net.eval()
        self.version += 1
        self.train_sets = m
        self.train_loss = float(torch.stack(losses).mean()) if losses else float("nan")
        return self.train_loss

    @torch.no_grad()
    def predict(self, keys: np.ndarray, label_history: np.ndarray | None = None,
                history_lengths: np.ndarray | None = None, batch_size: int = 4096) -> np.ndarray:
        """Predicted next value label of each set, float32 [M] in value units.

        With L > 1 the input uses the last L labels of the given histories (all of them, the
        newest included); without histories every step is padding (key only).
        """
        keys = np.asarray(keys, dtype=np.float32)
        self._ensure(keys)
        m = keys.shape[0]
        if m == 0:
            return np.zeros(0, np.float32)
        assert self.net is not None
        self.net.eval()
        out = []
        for i in range(0, m, batch_size):
            sl = slice(i, min(m, i + batch_size))
            if label_history is not None and history_lengths is not None and self.sequence_length > 1:
                lengths = np.asarray(history_lengths, dtype=np.int64)
                off = _offsets(lengths)
                # rebuild the flat history of this chunk (contiguous slice of the flat array)
                a = int(off[sl.start])
                b = int(off[sl.stop - 1] + lengths[sl.stop - 1])
                x = self._inputs(keys[sl], np.asarray(label_history)[a:b], lengths[sl],
                                 exclude_newest=False)
            elif self.sequence_length == 1 and self.device.type == "cpu" and self.kept_buffers:
                with self._input_rows.rows(sl.stop - sl.start, keys.shape[1]) as buf:
                    x = self._scaled(torch.from_numpy(keys[sl]), out=torch.from_numpy(buf))
                    out.append(self.net(x.unsqueeze(1)))
                continue
            else:
                x = self._inputs(keys[sl], None, None, exclude_newest=False)
            out.append(self.net(x))
        y = torch.cat(out).float().cpu().numpy()
        return (y * self.label_std + self.label_mean).astype(np.float32)

    def predict_transitions(self, transitions, key_fn: Callable = default_key_fn) -> np.ndarray:
        """QT(tau) for a batch of transitions (no label history), value units."""
        return self.predict(key_fn(transitions))

    # ---------------------------------------------------------------- serialisation
    def to_arrays(self) -> dict:
        """Everything needed to rebuild the model, as plain data (no pickles).

        Keys match :meth:`from_arrays`'s arguments and the fields of ``comper_msgs/QTModel``:
        architecture, config (JSON-serialisable dict), key_size, sequence_length, tensors
        (ordered name -> np.float32 array), input_mean, input_std, label_mean, label_std,
        version, train_loss, train_sets, format_version.
        """
        if self.net is None:
            raise RuntimeError("QT has no network yet (no key size known)")
        cfg = config_to_dict(self.config)
        cfg = {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in cfg.items()}
        return {
            "architecture": self.config.qt_architecture,
            "config": cfg,
            "key_size": int(self.key_dim),
            "sequence_length": self.sequence_length,
            "tensors": {name: t.detach().float().cpu().numpy().copy()
                        for name, t in self.net.state_dict().items()},
            "input_mean": self.input_mean.astype(np.float32).copy(),
            "input_std": self.input_std.astype(np.float32).copy(),
            "label_mean": float(self.label_mean),
            "label_std": float(self.label_std),
            "version": int(self.version),
            "train_loss": float(self.train_loss),
            "train_sets": int(self.train_sets),
            "format_version": QT_FORMAT_VERSION,
        }

    @classmethod
    def from_arrays(cls, *, config: dict, key_size: int, tensors: dict, input_mean, input_std,
                    label_mean: float, label_std: float, version: int = 0,
                    train_loss: float = float("nan"), train_sets: int = 0,
                    architecture: str | None = None, sequence_length: int | None = None,
                    format_version: int = QT_FORMAT_VERSION, device: str | None = None) -> "QTModel":
        """Rebuild a model from :meth:`to_arrays` output (or a ``QTModel`` message's fields).

        `device` overrides the config's qt_device (e.g. a learner on another machine). The running
        scaler's moments are not transported: a rebuilt model predicts; if it trains further its
        scaler restarts from the transported mean/std as a single-sample-weighted prior.
        """
        if format_version != QT_FORMAT_VERSION:
            raise ValueError(f"QT arrays of format {format_version}, expected {QT_FORMAT_VERSION}")
        values = dict(config)
        if device is not None:
            values["qt_device"] = device
        cfg = qt_config_for(architecture or values.get("qt_architecture", "comper"), values)
        if sequence_length is not None and sequence_length != cfg.qt_sequence_length:
            raise ValueError("sequence_length disagrees with the config")
        model = cls(cfg, key_dim=int(key_size))
        assert model.net is not None
        state = {k: torch.as_tensor(np.asarray(v, dtype=np.float32)) for k, v in tensors.items()}
        model.net.load_state_dict(state)
        model._set_scaler(np.asarray(input_mean, np.float32), np.asarray(input_std, np.float32),
                          float(label_mean), float(label_std), n=1)
        model.version, model.train_loss, model.train_sets = int(version), float(train_loss), int(train_sets)
        return model

    def _set_scaler(self, in_mean, in_std, lab_mean, lab_std, n: int) -> None:
        self.input_mean, self.input_std = in_mean.astype(np.float32), in_std.astype(np.float32)
        self.label_mean, self.label_std = float(lab_mean), float(lab_std)
        self._in.n, self._in.mean, self._in.m2 = n, in_mean.astype(np.float64), (in_std.astype(np.float64) ** 2) * n
        self._lab.n, self._lab.mean = n, np.array([lab_mean], np.float64)
        self._lab.m2 = np.array([lab_std ** 2 * n], np.float64)

    def state_dict(self) -> dict:
        """Torch-checkpointable state (tensors and primitives only): weights, optimiser, scaler
        moments, counters, config."""
        if self.net is None:
            return {"config": _plain(config_to_dict(self.config)), "key_dim": None}
        return {
            "config": _plain(config_to_dict(self.config)),
            "key_dim": int(self.key_dim),
            "net": self.net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scaler": {"in_n": self._in.n, "in_mean": torch.from_numpy(self._in.mean.copy()),
                       "in_m2": torch.from_numpy(self._in.m2.copy()), "lab_n": self._lab.n,
                       "lab_mean": torch.from_numpy(self._lab.mean.copy()),
                       "lab_m2": torch.from_numpy(self._lab.m2.copy())},
            "version": self.version, "train_loss": self.train_loss, "train_sets": self.train_sets,
            "shuffle_rng": self._gen.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        if state.get("key_dim") is None:
            return
        if self.net is None:
            self._build(int(state["key_dim"]))
        assert self.net is not None and self.optimizer is not None
        self.net.load_state_dict(state["net"])
        self.optimizer.load_state_dict(state["optimizer"])
        s = state["scaler"]
        self._in.n, self._in.mean, self._in.m2 = int(s["in_n"]), s["in_mean"].numpy(), s["in_m2"].numpy()
        self._lab.n, self._lab.mean, self._lab.m2 = int(s["lab_n"]), s["lab_mean"].numpy(), s["lab_m2"].numpy()
        self.input_mean = self._in.mean.astype(np.float32)
        self.input_std = self._in.std().astype(np.float32)
        self.label_mean, self.label_std = float(self._lab.mean[0]), float(self._lab.std()[0])
        self.version, self.train_loss, self.train_sets = int(state["version"]), float(state["train_loss"]), int(state["train_sets"])
        self._gen.set_state(state["shuffle_rng"])

    @classmethod
    def from_state_dict(cls, state: dict, device: str | None = None) -> "QTModel":
        values = dict(state["config"])
        if device is not None:
            values["qt_device"] = device
        model = cls(qt_config_for(values.get("qt_architecture", "comper"), values))
        model.load_state_dict(state)
        return model


def _plain(d: dict) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


@contextlib.contextmanager
def _round_keys(qt: QTModel, reps, key_fn: Callable):
    """The keys of a round's representatives: the default key builder writes them into the model's kept buffer."""
    if key_fn is not transition_keys or not qt.kept_buffers:
        yield key_fn(reps)
        return
    n = len(reps)
    dim = key_size_of(reps.states.shape[1:], np.asarray(reps.actions).reshape(n, -1).shape[1])
    with qt.key_rows.rows(n, dim) as buf:
        yield transition_keys(reps, out=buf)


def reduction_predictor(qt: QTModel, epochs: int | None = None,
                        key_fn: Callable = default_key_fn,
                        batch_size: int | None = None) -> Callable:
    """The callable a memory's reduce step uses: train QT on the lease's sets, then predict them.

    The lease needs attributes ``representatives`` (Transitions), ``label_history`` (float32
    flat, oldest first), ``history_lengths`` (uint32 [M], each >= 1) and ``counts``. Returns
    float32 [M] predictions in value units (the next label of each set; see module docstring).
    """

    def predict(lease) -> np.ndarray:
        reps = lease.representatives
        if len(reps) == 0:
            return np.zeros(0, np.float32)
        hist = np.asarray(lease.label_history, dtype=np.float32)
        lengths = np.asarray(lease.history_lengths, dtype=np.int64)
        with _round_keys(qt, reps, key_fn) as keys:
            qt.fit(keys, hist, lengths, epochs=epochs, batch_size=batch_size)
            return qt.predict(keys, hist, lengths)

    return predict
