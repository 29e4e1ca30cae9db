"""Hyper-parameters of the agent package (no torch, no ROS imports).

Each default is defined once, here, with the thesis value and where the thesis gives it. Defaults
that differ from the thesis's literal text (docs/method.md section 6) carry ``deviation=``.
Variants with other defaults (COMCACT's QT, the DQN baseline, the DDPG baseline) are subclasses
that redefine only the fields whose defaults differ, each again with its source.

Field names are flat (ROS parameters): QT fields carry a ``qt_`` prefix so that a node can declare
an agent config and a QT config side by side.

Size: one place defines every hyper-parameter of the agent package with its thesis value and source
(the suite's rule), so the learners, QT and the profiles read their defaults from this one module.
"""
from __future__ import annotations

from dataclasses import dataclass

from comper_msgs_py.params import param

__all__ = ["QTConfig", "ComcactQTConfig", "ComcactConfig", "DDPGConfig", "ComperConfig", "ALL_CONFIGS",
           "parameter_table_markdown",
           "DQNConfig", "qt_config_for", "QT_CONFIGS", "COMPER_PROFILES", "COMCACT_PROFILES", "resolve_profile",
           "resolve_comcact_profile", "thesis_differences",
           "profile_table_markdown"]

_NEXT_VALUE_DEVIATION = (
    "thesis text stores Q(s_t, a_t) with tau_t (q_sa), which makes r + gamma QT(tau) a target "
    "without next-state information; next_value labels each transition with the bootstrap value "
    "of s' (0 when terminated), making eq. 4.1 a proper TD target (method.md 6.1)")


# --------------------------------------------------------------------------------------------
# QT, the Q-target network
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class QTConfig:
    """COMPER's QT (Table 37 architecture, Table 33 optimiser)."""

    qt_architecture: str = param(
        "comper", "network layout: comper = Table 37, comcact = Appendix B (only a label; the "
        "layer sizes below define the network)", choices=("comper", "comcact"))
    qt_lstm_units: list[int] = param(
        [64, 32, 32], "units of the stacked LSTM layers (tanh), the last returns only its final output",
        thesis="64, 32, 32 (Table 37, appendix A.4)")
    qt_dense_units: int = param(18, "units of the ReLU dense layer after the LSTMs",
                                thesis="18 (Table 37)", minimum=1)
    qt_output_activation: str = param("linear", "activation of the 1-unit output layer",
                                      thesis="linear (appendix A.4)", choices=("linear", "tanh"))
    qt_output_init: float = param(
        0.0, "if > 0, the output layer's weights are drawn from U(-x, x) (bias 0); 0 = torch default",
        thesis="not given for COMPER (Keras default glorot-uniform)", minimum=0.0)
    qt_sequence_length: int = param(
        1, "L: 1 feeds the representative key as a length-1 sequence (the thesis's architecture); "
        "L > 1 feeds the L labels before the newest, each joined with the key (and a presence flag), "
        "and predicts the newest", thesis="input shape (1, key size) (Table 37)", minimum=1)
    qt_lr: float = param(2.5e-4, "RMSProp step size", thesis="0.00025 (Table 33)", minimum=0.0)
    qt_rms_alpha: float = param(0.9, "RMSProp decay (rho) of the squared-gradient average",
                                thesis="0.9 (Table 33)", minimum=0.0, maximum=1.0)
    qt_rms_eps: float = param(1e-10, "RMSProp epsilon added to the denominator",
                              thesis="1e-10 (Table 33)", minimum=0.0)
    qt_rms_momentum: float = param(0.0, "RMSProp momentum", thesis="0 (Table 33)", minimum=0.0)
    qt_batch_size: int = param(16, "mini-batch size of QT training", thesis="16 (appendix A.4)",
                               minimum=1)
    qt_epochs: int = param(1, "passes over the popped sets per reduction",
                           thesis="not given (Keras fit default 1)", minimum=1)
    qt_scaler: str = param(
        "running", "input/target scaler: running = mean/std accumulated over all training rounds "
        "(inputs the network already learned keep their scale), refit = refitted on each round's sets",
        choices=("running", "refit"))
    qt_grad_clip: float = param(0.0, "if > 0, clip the gradient norm of QT updates to this value",
                                minimum=0.0)
    qt_device: str = param("cpu", "torch device of QT (cpu, cuda, cuda:0, ...)")
    qt_seed: int = param(0, "seed of QT's initial weights and of its mini-batch shuffling", minimum=0)
    qt_compile: str = param(
        "off", "torch.compile of QT's RMSprop update for weights of 4M or more elements (COMPER's first layer "
        "on 4-frame Atari keys: 14.5M): one fused pass over them instead of five element-wise passes, the same "
        "arithmetic up to float rounding; off = eager (exact); default / max-autotune-no-cudagraphs = that "
        "torch.compile mode, compiled at the first step (seconds), eager with a warning if no C++ compiler is "
        "found or compiling fails (docs/studies/comper-speed.md)",
        choices=("off", "default", "max-autotune-no-cudagraphs"))


@dataclass(frozen=True)
class ComcactQTConfig(QTConfig):
    """COMCACT's QT (Appendix B)."""

    qt_architecture: str = param("comcact", "network layout: comper = Table 37, comcact = Appendix B",
                                 choices=("comper", "comcact"))
    qt_lstm_units: list[int] = param([64, 64], "units of the stacked LSTM layers (tanh)",
                                     thesis="64, 64 (appendix B)")
    qt_dense_units: int = param(32, "units of the ReLU dense layer after the LSTMs",
                                thesis="32 (appendix B)", minimum=1)
    qt_output_activation: str = param(
        "linear", "activation of the 1-unit output layer", thesis="tanh (appendix B)",
        choices=("linear", "tanh"),
        deviation="tanh would bound every Q-target to [-1, 1] while returns are far larger "
                  "(method.md 6.2)")
    qt_output_init: float = param(3e-4, "output layer weights drawn from U(-x, x) (bias 0)",
                                  thesis="U(-0.0003, 0.0003) (appendix B)", minimum=0.0)
    qt_lr: float = param(1e-3, "RMSProp step size", thesis="1e-3 (appendix B)", minimum=0.0)
    qt_rms_alpha: float = param(0.9, "RMSProp decay (rho)",
                                thesis="not given (Keras RMSprop default 0.9)", minimum=0.0, maximum=1.0)
    qt_rms_eps: float = param(1e-7, "RMSProp epsilon", thesis="not given (Keras RMSprop default 1e-7)",
                              minimum=0.0)
    qt_rms_momentum: float = param(0.0, "RMSProp momentum", thesis="not given (Keras default 0)",
                                   minimum=0.0)
    qt_batch_size: int = param(32, "mini-batch size of QT training",
                               thesis="not given (Keras fit default 32)", minimum=1)


QT_CONFIGS = {"comper": QTConfig, "comcact": ComcactQTConfig}   #: QT architecture -> its config class


def qt_config_for(architecture: str, values: dict | None = None):
    """The QT config of an architecture name (comper: Table 37, comcact: appendix B), built from
    `values` (validated; unknown names ignored)."""
    from comper_msgs_py.params import config_from_dict
    if architecture not in QT_CONFIGS:
        raise ValueError(f"QT architecture must be one of {', '.join(QT_CONFIGS)}, got {architecture!r}")
    return config_from_dict(QT_CONFIGS[architecture], values, ignore_unknown=True)


# --------------------------------------------------------------------------------------------
# COMCACT / DDPG
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ComcactConfig:
    """COMCACT (Algorithm 8, appendix B). The DDPG baseline is :class:`DDPGConfig`."""

    variant: str = param("comcact", "comcact = DDPG updates + the extra critic step towards "
                         "r + gamma (1 - terminated) QT(tau); ddpg = the QT step off (baseline)",
                         choices=("comcact", "ddpg"))
    qt_label: str = param("next_value", "value label stored with each transition: next_value = "
                          "Q(s', mu(s')) (0 when terminated); q_sa = Q(s, a) (thesis-literal)",
                          thesis="q_sa (Algorithm 8 line 8)", choices=("next_value", "q_sa"),
                          deviation=_NEXT_VALUE_DEVIATION)
    label_critic: str = param(
        "online", "networks that compute the value labels (next_value: Q(s', mu(s'))): online = the critic and "
        "actor being trained; target = the slowly moving target networks, the ones the DDPG target bootstraps from",
        thesis="online (Algorithm 8 line 8: Q with Theta^Q)", choices=("online", "target"),
        deviation="target: a QT fitted on these labels estimates the DDPG step's own bootstrap Q'(s', mu'(s')) "
        "instead of the faster-moving online critic's (method.md 6.4)")
    actor_hidden: list[int] = param([400, 300], "actor hidden layers (ReLU; batch norm after each if batch_norm)",
                                    thesis="400, 300 (appendix B)")
    critic_hidden: list[int] = param([400, 300], "critic hidden layers (ReLU)",
                                     thesis="400, 300 (appendix B)")
    batch_norm: bool = param(
        False, "batch normalisation of the state input and the hidden layers of actor and critic (false = "
        "plain MLPs, as Stable-Baselines3 / CleanRL DDPG)", thesis="yes (appendix B)",
        deviation="off: plain MLPs as Stable-Baselines3's and CleanRL's DDPG; with batch norm our DDPG fell into a "
        "saturated policy (docs/studies/comcact-batch-norm.md); -p batch_norm:=true is appendix B")
    qt_step_gate: bool = param(
        False, "comcact: skip the QT step on a batch where the QT target is farther from the DDPG target (RMS over "
        "the batch) than the critic's own TD error", thesis="off (every update takes the QT step)",
        deviation="on = the QT step only where it is closer to the DDPG target than the critic already is "
        "(docs/studies/comcact-qt-step-gate.md)")
    critic_action_input: str = param(
        "second_hidden", "where the action enters the critic: second_hidden = concatenated to the "
        "(batch-normalised) first hidden layer's output, the input of the second hidden layer "
        "(Lillicrap et al. 2016); output = after the second hidden layer (thesis-literal reading)",
        thesis="'after the second hidden layer' (appendix B)", choices=("second_hidden", "output"))
    actor_final_init: float = param(3e-3, "actor output layer weights and bias drawn from U(-x, x)",
                                    thesis="U(-0.003, 0.003) (appendix B)", minimum=0.0)
    critic_final_init: float = param(3e-4, "critic output layer weights and bias drawn from U(-x, x)",
                                     thesis="U(-0.0003, 0.0003) (appendix B)", minimum=0.0)
    actor_lr: float = param(1e-3, "Adam step size of the actor", thesis="1e-3 (appendix B)",
                            minimum=0.0)
    critic_lr: float = param(2e-3, "Adam step size of the critic (also used by the QT step)",
                             thesis="'20^-3' (appendix B), read as 2e-3", minimum=0.0)
    gamma: float = param(0.99, "discount factor", thesis="0.99 (appendix B)", minimum=0.0, maximum=1.0)
    tau: float = param(0.005, "soft target update rate", thesis="0.005 (appendix B)",
                       minimum=0.0, maximum=1.0)
    batch_size: int = param(64, "transitions per update, sampled uniformly from RTM (or the replay "
                            "buffer for ddpg)", thesis="64 (appendix B)", minimum=2)
    learning_starts: int = param(64, "first update once the memory holds this many transitions "
                                 "(batch norm needs a batch)",
                                 thesis="not given (Algorithm 8 updates from the first step)", minimum=0)
    ou_theta: float = param(0.15, "Ornstein-Uhlenbeck mean reversion", thesis="0.15 (section 4.2)",
                            minimum=0.0)
    ou_sigma: float = param(0.2, "Ornstein-Uhlenbeck volatility", thesis="0.2 (section 4.2)",
                            minimum=0.0)
    ou_dt: float = param(1.0, "Ornstein-Uhlenbeck time step (1.0 = the discrete process of "
                         "Lillicrap et al.; the Keras DDPG example uses 0.01)",
                         thesis="not given", minimum=0.0)
    noise_relative_to_bounds: bool = param(
        True, "true: OU noise is in normalised action units, scaled by (high - low) / 2 before it is "
        "added; false: added in raw action units")
    replay_size: int = param(100_000, "capacity of the plain replay buffer (ddpg baseline)",
                             thesis="not given (runs have 50,000 steps; nothing is overwritten)",
                             minimum=1)
    grad_clip: float = param(0.0, "if > 0, clip actor and critic gradient norms to this value",
                             minimum=0.0)
    device: str = param("cpu", "torch device of the learner (cpu, cuda, ...)")
    learner_compile: str = param(
        "off", "torch.compile of the update's loss and target functions (same arithmetic up to float rounding): "
        "off = eager; default / max-autotune-no-cudagraphs = that torch.compile mode, compiled on the first "
        "update (seconds to minutes, reported as the train/compile_s scalar), eager with a warning if no C++ compiler "
        "is found or compiling fails (docs/studies/agent-core-learner-step-speed.md)",
        choices=("off", "default", "max-autotune-no-cudagraphs"))
    num_threads: int = param(2, "torch intra-op threads, set by the entry point", minimum=1)
    seed: int = param(0, "seed of network initialisation, noise and replay sampling", minimum=0)


@dataclass(frozen=True)
class DDPGConfig(ComcactConfig):
    """DDPG baseline: the COMCACT learner with the QT step off and a plain replay buffer."""

    variant: str = param("ddpg", "comcact or ddpg (baseline, QT step off)",
                         choices=("comcact", "ddpg"))


# --------------------------------------------------------------------------------------------
# COMPER / DQN
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ComperConfig:
    """COMPER (Algorithm 7, appendix A). The DQN baseline is :class:`DQNConfig`."""

    variant: str = param(
        "comper", "comper = target r + gamma (1 - terminated) QT(tau), RTM sampling; comper_m = the "
        "same target, sampling from TM; comper_f = RTM sampling with the DQN target network; "
        "dqn = replay buffer + target network (baseline)",
        choices=("comper", "comper_m", "comper_f", "dqn"))
    qt_label: str = param("next_value", "value label stored with each transition: next_value = "
                          "max_a Q(s', a) (0 when terminated); q_sa = Q(s, a) (thesis-literal)",
                          thesis="q_sa (Algorithm 7 line 4: Q_t from epsilon-greedy)",
                          choices=("next_value", "q_sa"), deviation=_NEXT_VALUE_DEVIATION)
    qt_target_gate: bool = param(
        False, "comper, comper_m: per batch, bootstrap from the target network B(s') (as comper_f: Q_target(s', "
        "argmax_a Q(s', a)) with double_dqn, max_a Q_target(s', a) without) instead of QT(tau) when QT is off from "
        "what it is fitted to by more than that varies between the batch's states: RMS over non-terminal rows of "
        "QT(tau) - V(s') > their standard deviation of V(s'), V(s') = max_a Q(s', a), the value labels' bootstrap. "
        "Adds a target network, copied every target_update_every agent steps",
        thesis="off (Algorithm 7: QT gives every TD target; there is no target network)",
        deviation="on = QT's target only where it carries more of the state-dependent bootstrap than it loses in "
        "error (docs/studies/comper-qt-gate-label.md)")
    n_actions: int = param(0, "outputs of the Q-network; 0 = the environment's action count (an ALE game "
                           "with the full action set: 18)", thesis="18 (appendix A.4, the ALE full action set)",
                           minimum=0)
    q_network: str = param(
        "auto", "Q-network: nature_cnn (Table 36, uint8 frames) | mlp (vector observations, mlp_hidden) | auto = "
        "nature_cnn for image observations ([84, 84] or [C, 84, 84]), mlp for 1-D observations",
        thesis="nature_cnn (Table 36; the thesis runs only Atari)", choices=("auto", "nature_cnn", "mlp"))
    mlp_hidden: list[int] = param(
        [256, 256], "hidden layers (ReLU) of the mlp Q-network",
        thesis="not given (no vector tasks in the thesis); 256, 256 as rl-baselines3-zoo's DQN on CartPole-v1")
    frame_stack: int = param(1, "frames per observation (input channels; ALE only, vector tasks use 1)",
                             thesis="1 single frame, 4 stacked (Table 34)", minimum=1)
    optimizer: str = param(
        "rmsprop_dm", "rmsprop_dm = DeepMind's centred RMSProp (lr and the rms_* values below); adam = "
        "torch.optim.Adam (lr, adam_eps)", thesis="RMSProp of Table 32", choices=("rmsprop_dm", "adam"))
    lr: float = param(2.5e-4, "step size of the optimizer", thesis="0.00025 (Table 32)", minimum=0.0)
    adam_eps: float = param(1.5e-4, "Adam epsilon (optimizer adam only)",
                            thesis="not used (RMSProp); 1.5e-4 is DER's (van Hasselt et al. 2019)", minimum=0.0)
    loss_reduction: str = param(
        "sum", "how one batch's per-transition Huber losses make the loss: sum = the gradient is the sum of the "
        "clipped TD errors over the batch; mean = divided by the batch's size B, and with rmsprop_dm the min "
        "squared gradient is divided by B^2 at each update, which gives exactly the sum's step (g, n and the "
        "gradient all scale by 1/B, so lr grad / sqrt(n - g^2 + c) is unchanged when c scales by 1/B^2)",
        thesis="sum (Algorithm 7 lines 14-21 accumulate the gradient over the k transitions before one step, "
        "as DeepMind's DQN, for which Table 32's 0.01 is sized)", choices=("sum", "mean"))
    reward_clip: str = param(
        "clip", "reward in the learning signal (TD targets, so also the value labels and QT, which learn "
        "them): clip = clamped to [-1, 1] (for integer game scores this is the sign), sign = the sign of the "
        "reward, none = raw. Episode scores in logs, summaries, topics and bags, and the rewards stored in "
        "the memory (part of the similarity key), are the raw game score; with n_step > 1 the COMPER variants "
        "store each window's return of clipped rewards instead",
        thesis="clipped to [-1, 1] (chapter 5 follows Machado et al. 2018, whose DQN clips rewards as Mnih "
        "et al. 2015)", choices=("clip", "sign", "none"))
    double_dqn: bool = param(
        False, "variants with a target network (comper_f, dqn; comper and comper_m with qt_target_gate): "
        "bootstrap from Q_target(s', argmax_a Q(s', a)) (double DQN, van Hasselt et al. 2016) instead "
        "of max_a Q_target(s', a)",
        thesis="false (the DQN of Mnih et al. 2015 and Machado et al. 2018)")
    n_step: int = param(
        1, "transitions per TD target; n > 1 bootstraps from the state n steps on: sum_j<m gamma^j clip(r_j) + "
        "gamma^m (1 - terminated) bootstrap(s_m) (the rewards of the behaviour policy, uncorrected, as in "
        "Rainbow and DER). dqn: the replay cuts each drawn window (m <= n) at the episode's end or the newest "
        "stored transition. comper, comper_f, comper_m: the memory stores n-step transitions (s_t, a_t, the "
        "window's return, s_{t+n}) labelled max_a Q(s_{t+n}, a), and QT or the target network bootstraps "
        "s_{t+n} with gamma^n; windows ended by a termination are kept, those cut short by a truncation are "
        "dropped (memory_schedule.NStepWindows). Deviation for n > 1 (method.md 6.6); not with qt_label q_sa",
        thesis="1 (one-step Q-learning: Algorithm 7 and the DQN of Table 35)", minimum=1)
    rms_grad_momentum: float = param(0.95, "RMSProp gradient (mean) momentum",
                                     thesis="0.95 (Table 32)", minimum=0.0, maximum=1.0)
    rms_sq_grad_momentum: float = param(0.95, "RMSProp squared-gradient momentum",
                                        thesis="0.95 (Table 32)", minimum=0.0, maximum=1.0)
    rms_min_sq_grad: float = param(0.01, "constant added inside the RMSProp denominator's sqrt",
                                   thesis="0.01 (Table 32)", minimum=0.0)
    gamma: float = param(0.99, "discount factor", thesis="0.99 (method.md 4)", minimum=0.0,
                         maximum=1.0)
    huber_delta: float = param(1.0, "Huber loss threshold (error clipping of Mnih et al. 2015)",
                               thesis="Huber loss (method.md 4)", minimum=0.0)
    batch_size: int = param(32, "transitions per update", thesis="32 (Table 34)", minimum=1)
    train_frequency: int = param(4, "agent steps between updates", thesis="4 (Table 34)", minimum=1)
    learning_starts: int = param(
        100, "agent steps (not frames) before the first update; epsilon follows its own schedule from step 0",
        thesis="100 (Table 34, 'replay start size', given in frames; counted here in agent steps as the "
        "DQN code of Mnih et al. 2015 does)", minimum=0)
    epsilon_start: float = param(1.0, "initial epsilon", thesis="1.0 (method.md 4)", minimum=0.0,
                                 maximum=1.0)
    epsilon_end: float = param(0.01, "final epsilon", thesis="0.01 (method.md 4)", minimum=0.0,
                               maximum=1.0)
    epsilon_decay_frames: int = param(90_000, "emulator frames (counting skipped ones; a vector task has "
                                      "one frame per agent step) over which epsilon decays linearly",
                                      thesis="90,000 (method.md 4)", minimum=1)
    target_update_every: int = param(1_000, "agent steps between target-network copies "
                                     "(comper_f, dqn; comper and comper_m with qt_target_gate)", thesis="1,000 (Table 35)",
                                     minimum=1)
    frame_pooling: str = param(
        "average", "how an ALE observation combines the last two frames of a skip (given to the embedded sim "
        "node's frame_pooling): average = colour averaging (Machado et al. 2018), max = per-pixel maximum "
        "(Mnih et al. 2015)", thesis="colour averaging for COMPER (Table 34)", choices=("average", "max"))
    replay_size: int = param(100_000, "replay buffer capacity (dqn)", thesis="100,000 (Table 35)",
                             minimum=1)
    device: str = param("cpu", "torch device of the learner (cpu, cuda, ...)")
    num_threads: int = param(2, "torch intra-op threads, set by the entry point", minimum=1)
    seed: int = param(0, "seed of network initialisation, exploration and replay sampling", minimum=0)

    @property
    def window_rewards(self) -> bool:
        """Whether the learner samples stored n-step windows (a COMPER variant with n_step > 1,
        memory_schedule.NStepWindows): their rewards are already clipped and discounted and their bootstrap is
        n steps on, discounted by gamma^n_step. dqn forms its windows from the replay at sampling time."""
        return self.n_step > 1 and self.variant != "dqn"


@dataclass(frozen=True)
class DQNConfig(ComperConfig):
    """DQN baseline (Table 35)."""

    variant: str = param("dqn", "comper, comper_m, comper_f or dqn",
                         choices=("comper", "comper_m", "comper_f", "dqn"))
    frame_stack: int = param(4, "frames per observation (input channels)",
                             thesis="4 (Table 35)", minimum=1)
    learning_starts: int = param(1_000, "agent steps (not frames) before the first update",
                                 thesis="1,000 (Table 35, 'replay start size', in frames; counted in agent steps)",
                                 minimum=0)
    frame_pooling: str = param("max", "ALE: how the last two frames of a skip combine: average | max",
                               thesis="max, 'frame pooling' (Table 35)", choices=("average", "max"))


# --------------------------------------------------------------------------------------------
# comper_node profiles: named sets of learner defaults, each value with its source
# --------------------------------------------------------------------------------------------
_PACE = ("re-storing each update's batch reopens its sets, 100 steps x (1 + batch / train_frequency) = 3,300 "
         "per reduce_every; Table 34's 1,000 fits 100 x (1 + 32 / 4) = 900, and behind it TM grows and QT's "
         "targets go stale")

#: profile -> {field: (value, source)}. A profile only changes defaults: `-p name:=value` still wins.
#: thesis = the dataclass defaults above (Algorithm 7, Tables 32-35).
COMPER_PROFILES: dict[str, dict[str, tuple]] = {
    "thesis": {},
    # Short Atari budgets: the settings of Data-Efficient Rainbow (van Hasselt et al. 2019) as Dopamine's
    # atari_100k DER.gin gives them, minus what is not DQN (n-step returns, distributional, dueling, noisy
    # nets, prioritised replay are not implemented)
    "data_efficient": {
        "optimizer": ("adam", "DER.gin: JaxDQNAgent.optimizer adam"),
        "lr": (1e-4, "DER.gin: create_optimizer.learning_rate 0.0001 (van Hasselt et al. 2019)"),
        "adam_eps": (1.5e-4, "DER.gin: create_optimizer.eps 0.00015"),
        "loss_reduction": ("mean", "Dopamine's DQN loss is the batch mean (Adam's step barely depends on scale)"),
        "train_frequency": (1, "DER.gin: update_period 1 (one update per agent step)"),
        "frame_stack": (4, "Dopamine's Atari preprocessing stacks 4 frames"),
        "double_dqn": (True, "DER.gin: double_dqn True"),
        "target_update_every": (2_000, "DER.gin: target_update_period 2000 (= agent steps at update_period 1)"),
        "learning_starts": (1_600, "DER.gin: min_replay_history 1600 agent steps"),
        "epsilon_decay_frames": (10_000, "DER.gin: epsilon_decay_period 2000 agent steps, x frame skip 5"),
        "epsilon_end": (0.01, "DER.gin: epsilon_train 0.01"),
        "reduce_batch": (4_000, "keeps the reduction at the stores' pace (as classic_control; not measured on "
                                "Atari): " + _PACE),
    },
    # The default on ALE games: data_efficient with 10-step targets and the QT-target gate's label test, the one
    # COMPER configuration measured above random play on Asterix, Seaquest and Freeway with 5 seeds each
    # (docs/studies/comper-qt-gate-label.md); reduce_overlap as those runs had it
    "atari_100k": {},      # filled below from data_efficient
    # Vector observations (CartPole-v1, Acrobot-v1, MountainCar-v0), which the thesis does not run:
    # rl-baselines3-zoo's DQN settings for CartPole-v1 (hyperparams/dqn.yml), mapped onto one update every
    # train_frequency steps. Checked with the learner alone on CartPole-v1: 3 of 3 seeds at 500 by 35,000 steps
    "classic_control": {
        "optimizer": ("adam", "rl-baselines3-zoo dqn.yml (SB3 DQN uses Adam)"),
        "lr": (2.3e-3, "rl-baselines3-zoo CartPole-v1: learning_rate 2.3e-3"),
        "adam_eps": (1e-8, "torch / SB3 Adam default"),
        "loss_reduction": ("mean", "SB3 DQN: smooth L1 (Huber) loss, batch mean"),
        "batch_size": (64, "rl-baselines3-zoo CartPole-v1: batch_size 64"),
        "train_frequency": (2, "rl-baselines3-zoo CartPole-v1: 128 gradient steps per 256 env steps"),
        "learning_starts": (1_000, "rl-baselines3-zoo CartPole-v1: learning_starts 1000"),
        "target_update_every": (256, "rl-baselines3-zoo CartPole-v1: the target is refreshed once per 256-step "
                                     "collection (target_update_interval 10 env steps, train_freq 256)"),
        "epsilon_decay_frames": (8_000, "rl-baselines3-zoo CartPole-v1: exploration_fraction 0.16 of 50,000 steps "
                                        "(one frame per step on vector tasks)"),
        "epsilon_end": (0.04, "rl-baselines3-zoo CartPole-v1: exploration_final_eps 0.04"),
        "double_dqn": (False, "SB3 DQN, whose settings these are, is not double DQN"),
        "replay_size": (100_000, "rl-baselines3-zoo CartPole-v1: buffer_size 100000"),
        "reward_clip": ("none", "classic control rewards are already -1 / +1 per step"),
        "frame_stack": (1, "a vector observation is the whole state (the DQN baseline's 4 applies to frames)"),
        "reduce_batch": (4_000, "keeps the reduction at the stores' pace: " + _PACE +
                         " (docs/studies/comper-vector-tasks.md)"),
    },
}


COMPER_PROFILES["atari_100k"] = {
    **COMPER_PROFILES["data_efficient"],
    "n_step": (10, "10-step targets: above 1-step COMPER on all three games (docs/studies/comper-n-step-compact-memory.md)"),
    "qt_target_gate": (True, "docs/studies/comper-qt-gate-label.md"),
    "reduce_overlap": (True, "the engineering setting of the runs behind this profile: reductions overlap learning "
                             "on the second core"),
}

# comcact_node profiles. Unlike COMPER's, their sources are this suite's own benchmark runs (50,000 steps, 3-5 seeds,
# 10 evaluation episodes every 5,000; docs/results.md)
#: profile -> {field: (value, source)}, as COMPER_PROFILES. The parameter defaults are Algorithm 8 and appendix B with
#: this suite's three engineering settings (plain MLPs, a store and a reduction every 10 steps: `plain`, the DDPG
#: baseline's profile); `thesis` puts those three back to the text
COMCACT_PROFILES: dict[str, dict[str, tuple]] = {
    "thesis": {
        "batch_norm": (True, "appendix B: batch normalisation in actor and critic"),
        "store_every": (1, "Algorithm 8: each transition is stored at its step"),
        "reduce_every": (1, "Algorithm 8 lines 27-28: a reduction every iteration"),
    },
    # the defaults; the DDPG baseline's profile (resolve_comcact_profile)
    "plain": {},
    # the default of algorithm comcact (resolve_comcact_profile)
    "fresh_labels_gate": {
        "restore_batch": (True, "docs/studies/comcact-four-task-ablation.md: with label_critic target, above the "
                                "thesis profile on all four tasks"),
        "label_critic": ("target", "docs/studies/comcact-four-task-ablation.md: QT's target error below the "
                                   "critic's own TD error in every run"),
        "qt_step_gate": (True, "docs/studies/comcact-qt-step-gate.md: at DDPG's level on Walker2d-v4, "
                               "HalfCheetah-v4 and InvertedDoublePendulum-v4"),
    },
}


def resolve_profile(name: str, env_id: str) -> str:
    """comper_node's ``profile``: auto -> atari_100k for ALE games (ALE/...), classic_control for other tasks."""
    if name == "auto":
        return "atari_100k" if env_id.startswith("ALE/") else "classic_control"
    if name not in COMPER_PROFILES:
        raise ValueError(f"unknown profile {name!r}; one of auto, {', '.join(COMPER_PROFILES)}")
    return name


def resolve_comcact_profile(name: str, algorithm: str) -> str:
    """comcact_node's ``profile``: auto -> fresh_labels_gate for comcact, plain for the DDPG baseline (the other
    profiles set COMCACT's labels and QT step, which ddpg does not have)."""
    if name == "auto":
        return "fresh_labels_gate" if algorithm == "comcact" else "plain"
    if name not in COMCACT_PROFILES:
        raise ValueError(f"unknown profile {name!r}; one of auto, {', '.join(COMCACT_PROFILES)}")
    if algorithm != "comcact" and name not in ("thesis", "plain"):
        raise ValueError(f"profile:={name} sets COMCACT's value labels and QT step, which ddpg does not have; "
                         "use profile:=plain (or auto, or thesis) with algorithm:=ddpg")
    return name


def profile_table_markdown(node_config=None, node: str = "comper") -> str:
    """A markdown table of a node's profiles (node: comper -> COMPER_PROFILES over ComperConfig, comcact ->
    COMCACT_PROFILES over ComcactConfig): each value that differs from the parameter defaults and its source.
    node_config: the node's parameter class, for profile values that are node parameters."""
    from comper_msgs_py.params import spec_of
    profiles, learner, empty = {
        "comper": (COMPER_PROFILES, ComperConfig, "Algorithm 7, Tables 32-35"),
        "comcact": (COMCACT_PROFILES, ComcactConfig, "Algorithm 8 and appendix B with the engineering settings "
                                                     "the thesis profile puts back")}[node]
    defaults = {f.name: d for f, d, _ in spec_of(node_config)} if node_config is not None else {}
    defaults.update({f.name: d for f, d, _ in spec_of(learner)})
    rows = ["| profile | parameter | value | default | source |", "|---|---|---|---|---|"]
    for name, values in profiles.items():
        if not values:
            rows.append(f"| `{name}` | (all) | the defaults | | {empty} |")
        for k, (v, src) in values.items():
            rows.append(f"| `{name}` | `{k}` | `{v}` | `{defaults[k]}` | {src} |")
    return "\n".join(rows) + "\n"


def thesis_differences(*configs, thesis: dict | None = None) -> list[str]:
    """What a run does differently from ``profile:=thesis``, for the start-up log: each parameter with a thesis
    value whose value is not the thesis profile's ('name=value (thesis: value)'), whether a profile or the command
    line set it. The thesis profile's own corrections of the thesis text are listed in method.md 6.
    configs: config instances (node parameters, learner hyper-parameters); thesis: the node's thesis profile
    ({field: (value, source)}; its values replace the parameter defaults)."""
    from comper_msgs_py.params import spec_of
    out = []
    for cfg in configs:
        for f, default, _ in spec_of(type(cfg)):
            if not (f.metadata.get("thesis") or f.metadata.get("deviation")):
                continue            # engineering settings (paths, threads, timeouts) have no thesis value
            if thesis and f.name in thesis:
                default = thesis[f.name][0]
            value = getattr(cfg, f.name)
            same = (list(value) == list(default)) if isinstance(value, (list, tuple)) else value == default
            if not same:
                out.append(f"{f.name}={value!r} (thesis: {default!r})")
    return out


def parameter_table_markdown(cls) -> str:
    """A markdown table of a config class: name, default, thesis value, description, deviation."""
    from comper_msgs_py.params import spec_of

    def cell(x) -> str:
        return str(x).replace("|", "\\|").replace("\n", " ")

    doc = (cls.__doc__ or "").strip()
    if doc.startswith(f"{cls.__name__}("):     # the signature dataclass writes for a class without a docstring
        doc = ""
    rows = [f"### {cls.__name__}", "", *([doc, ""] if doc else []),
            "| parameter | default | thesis | description | deviation |", "|---|---|---|---|---|"]
    for f, default, _ in spec_of(cls):
        m = f.metadata
        desc = m.get("description", "")
        if m.get("choices"):
            desc += f" ({' / '.join(map(str, m['choices']))})"
        rows.append(f"| `{f.name}` | `{cell(default)}` | {cell(m.get('thesis') or '')} | {cell(desc)} "
                    f"| {cell(m.get('deviation') or '')} |")
    return "\n".join(rows) + "\n"


ALL_CONFIGS = (QTConfig, ComcactQTConfig, ComcactConfig, DDPGConfig, ComperConfig, DQNConfig)
