"""The learner nodes' parameters, one place (each a ``param()`` field with its description, thesis
value and range; ``--help`` and the docs are built from them).

* :class:`AgentRunConfig` - what every learner node declares: bring-up, outputs, recording, node
  names, timeouts, and the reduction parameters both algorithms share.
* :class:`ComperNodeConfig`, :class:`ComcactNodeConfig` - each node's own parameters (the
  learners' hyper-parameters are in :mod:`comper_agent.core.config`).
* :class:`QtTrainerNodeConfig` - qt_trainer_node's own parameters (QT's are QTConfig /
  ComcactQTConfig, chosen by ``architecture``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from comper_msgs_py.params import param
from comper_sim.core import EPISODE_END_RULES
from comper_agent.core.config import COMCACT_PROFILES

__all__ = ["AgentRunConfig", "ComperNodeConfig", "ComcactNodeConfig", "QtTrainerNodeConfig", "ActorNodeConfig",
           "redefault", "comper_reducer", "reduce_pace_warning", "check_frames",
           "COMPER_ALGORITHMS"]

COMPER_ALGORITHMS = ("comper", "comper_f", "comper_m", "dqn")


def comper_reducer(p, cfg) -> str:
    """comper_node's parameters taken together (`p`: ComperNodeConfig, `cfg`: its learner's): refuses what cannot
    run (frame_stack on a vector task, n-step targets with q_sa labels, a QT variant without the QT trainer);
    returns the reducer: qt_trainer, memory (reducer auto: comper_f), or none (dqn: no memory)."""
    if not p.env_id.startswith("ALE/") and cfg.frame_stack != 1:
        raise ValueError(f"frame_stack:={cfg.frame_stack} applies to ALE games; {p.env_id} has vector "
                         "observations (use frame_stack:=1, or profile:=classic_control)")
    uses_memory = p.algorithm != "dqn"
    if cfg.n_step > 1 and uses_memory and cfg.qt_label == "q_sa":
        raise ValueError(f"n_step:={cfg.n_step} needs qt_label:=next_value: a q_sa label (Q(s_t, a_t)) "
                         "is not the bootstrap of s_(t+n)")
    reducer = p.reducer if p.reducer != "auto" else ("memory" if p.algorithm == "comper_f" else "qt_trainer")
    if not uses_memory:
        return "none"
    if p.algorithm in ("comper", "comper_m") and reducer != "qt_trainer":
        raise ValueError(f"{p.algorithm} needs QT: use reducer:=qt_trainer (or auto)")
    return reducer


def reduce_pace_warning(p, cfg) -> str:
    """comper_node: a warning when ``reduce_batch`` is below the TM sets stored into between two reductions
    (:func:`~comper_agent.core.memory_schedule.sets_touched_per_reduction`), else ''."""
    from comper_agent.core.memory_schedule import sets_touched_per_reduction
    touched = sets_touched_per_reduction(p.reduce_every, cfg.batch_size, cfg.train_frequency, p.restore_batch)
    if p.reduce_batch >= touched:
        return ""
    return (f"reduce_batch {p.reduce_batch} < up to {touched} sets stored into between two reductions (reduce_every "
            f"{p.reduce_every} x (1 + batch {cfg.batch_size} / train_frequency {cfg.train_frequency})): TM may fall "
            f"behind and QT's targets go stale; -p reduce_batch:={touched} or more keeps pace (docs/comper.md)")


def check_frames(obs_shape: tuple, spec: dict, cfg) -> str:
    """comper_node on an ALE game: ValueError when the sim's observations do not have the learner's frame stack;
    a warning when the sim pools frames otherwise than ``frame_pooling`` (else '')."""
    want = (84, 84) if cfg.frame_stack == 1 else (cfg.frame_stack, 84, 84)
    if obs_shape != want:
        raise ValueError(f"the sim serves observations {list(obs_shape)} but frame_stack:={cfg.frame_stack} "
                         f"needs {list(want)}; start the sim with -p frame_stack:={cfg.frame_stack}")
    pooling = spec.get("frame_pooling", "average")
    if pooling in ("average", "max") and pooling != cfg.frame_pooling:
        return (f"the sim pools frames by {pooling} but frame_pooling:={cfg.frame_pooling} "
                f"(start the sim with -p frame_pooling:={cfg.frame_pooling})")
    return ""


def redefault(cls, name: str, default):
    """A config field of `cls` (description, thesis, range) with another default, for a subclass:
    ``progress_period_s: float = redefault(AgentRunConfig, "progress_period_s", 10.0)``."""
    (f,) = [f for f in dataclasses.fields(cls) if f.name == name]
    return dataclasses.field(default=default, metadata=f.metadata)


@dataclass(frozen=True)
class AgentRunConfig:
    """Run set-up shared by the learner nodes; a node's config subclasses it with its algorithm's
    parameters (and redefines algorithm, env_id and the defaults that differ)."""

    algorithm: str = param("", "learning algorithm (each node lists its own)")
    bringup: str = param(
        "embedded", "embedded: build the sim, memory and QT trainer nodes in this process; external: use "
        "nodes started separately, named by sim_node, memory_node, qt_trainer_node",
        choices=("embedded", "external"))
    env_id: str = param("", "gymnasium task (embedded: given to the sim node; external: must match the "
                            "running sim node)")
    episode_end: str = param(
        "standard", "embedded sim node's episode end rule (method.md 6.3; only terminated masks the "
        "bootstrap; an ALE game over always ends the episode). External: the sim's rule is used",
        choices=EPISODE_END_RULES)
    runs_root: str = param("runs", "folder holding the run directories")
    run_id: str = param("", "run directory name; '' = <algorithm>-<env>-s<seed>-<timestamp>")
    resume: str = param(
        "", "checkpoint file or run directory to continue from ('' = fresh run). The run continues in "
        "the checkpoint's run directory with its step count and, where the checkpoint holds them "
        "(checkpoint_replay), the memory's or replay buffer's contents; the resumed step starts a new episode")
    checkpoint_replay: bool = param(
        True, "each checkpoint also saves the experience the learner samples: the memory node's state (a "
        "snapshot through its ~/snapshot service; embedded: step_<N>.memory beside the checkpoint, external: "
        "<run_id>/step_<N>.memory under the memory node's snapshot_root) or the local replay buffer "
        "(step_<N>.replay.npz); resume restores it. false = weights and counters only, the memory refills "
        "after a resume")
    keep_checkpoints: int = param(3, "step_<N>.pt files kept besides latest.pt (0 = keep all), and the newest one that "
                                 "holds the memory / replay contents", minimum=0)
    progress_period_s: float = param(5.0, "seconds between console progress lines", minimum=0.0)
    tensorboard: bool = param(True, "write TensorBoard scalars to <run dir>/tb")
    record: bool = param(
        False, "record this run's topics (transitions, episodes, evaluations, memory stats, sim episodes) "
        "into a rosbag2 bag in <run dir>/bag with a recorder_node (docs/recording.md)")
    record_storage: str = param("mcap", "bag storage when record is on", choices=("mcap", "sqlite3"))
    record_compression: str = param(
        "zstd", "bag compression when record is on: zstd (MCAP: compressed chunks, as ros2 bag record writes them; "
        "sqlite3: each message) or none", choices=("zstd", "none"))
    record_process: str = param(
        "child", "where record:=true runs its recorder_node: 'child' = a child process (its work runs on "
        "another core; the agent waits until it has subscribed, hands every message over before stopping it, "
        "and if the agent dies, even by SIGKILL, the recorder gets SIGTERM and closes the bag; its log is "
        "<run dir>/recorder.log), 'in_process' = a node on this process's executor (one process; costs "
        "~4-5 percent of the training throughput on Hopper-v4, docs/recording.md)", choices=("child", "in_process"))
    record_window: int = param(
        50, "record:=true: most training episodes published but not yet written by the recorder; the agent waits "
        "beyond it (flow control from the recorder's ~/status). Below the topics' history depth (100), so no "
        "reliable queue drops an episode when the agent outpaces the recorder", minimum=1, maximum=99)
    record_wait_s: float = param(
        60.0, "record:=true: longest wait for the recorder to catch up; after it the backlog is written off with "
        "a warning and training goes on", minimum=0.0)
    publish_transitions: bool = param(
        True, "publish each finished training episode's transitions (with the labels stored) on "
        "~/transitions, before its ~/episodes summary, while someone subscribes (record:=true does)")
    prefetch_batches: int = param(
        32, "most update batches fetched from the memory in one sample call. Only the batches of the updates "
        "before the next reduction are fetched (RTM does not change in between), each an independent uniform "
        "draw, so the batches are those of one call per update; sampling from TM (while RTM is empty, or "
        "COMPER-M) stays one call per update. 1 = one sample call per update",
        thesis="one draw per update (Algorithms 7 and 8); same distribution", minimum=1)
    reduce_overlap: bool = param(
        False, "send each reduction and go on learning (acting, updates from the current RTM, targets from the "
        "current QT) while the QT trainer and the memory reduce, on the other core; at most one reduction in "
        "flight (the next one waits for it), the first (RTM empty) is waited for; the new RTM and QT are used "
        "from the step their answer arrives (variants that reduce)",
        thesis="the agent waits for each reduction (Algorithms 7 and 8: reduce, then learn)",
        deviation="on = updates between a reduction's request and its answer use the RTM and QT of the "
        "previous reduction")
    reduce_batch: int = param(
        1_000, "most similar-transition sets popped from TM per reduction (0 = the reducer's own reduce_batch)",
        thesis="1,000 for COMPER (Table 34), 50,000 for COMCACT (appendix B)", minimum=0)
    qt_epochs: int = param(0, "QT training passes per reduction; 0 = the QT trainer's qt_epochs (default 1, "
                              "Keras fit default)", thesis="not given", minimum=0)
    qt_targets: str = param(
        "local", "where QT(tau) for the QT target comes from: local = predicted by the latest QTModel received "
        "(Algorithm 7 line 16, Algorithm 8 lines 29-30); rtm = the prediction RTM stored at the entry's last "
        "reduction (returned by sample; COMPER-M samples TM and always predicts locally)",
        choices=("local", "rtm"))
    qt_wait_s: float = param(2.0, "after a reduction, seconds to wait for the QTModel of that version to "
                                  "arrive (variants with a QT target)", minimum=0.0)
    diagnostics_every: int = param(
        250, "updates between 'qt_diagnostics' records in metrics.jsonl (and TensorBoard qt/...), for the variants "
        "with a QT target: on the update's batch, QT's bootstrap against the one the learner's own networks give "
        "(comcact: the DDPG target; comper, comper_m: max_a Q(s', a)), the TD error, the sampled entries' age "
        "and set sizes; comper also the Q gap between actions and the share of the batch on one greedy action "
        "(docs/comcact.md, docs/comper.md); 0 = off", minimum=0)
    eval_episodes: int = param(10, "full episodes per evaluation (greedy policy, a separate environment in "
                                   "this process)", thesis="10 (chapter 6)", minimum=1)
    eval_seed: int = param(
        -1, "seed of the evaluation environment's resets (episode k of every evaluation starts from seed "
        "eval_seed + k); -1 = seed + 1000", minimum=-1)
    sim_node: str = param("sim_node", "name of the simulation node")
    memory_node: str = param("memory_node", "name of the memory node (not used by the baselines)")
    qt_trainer_node: str = param("qt_trainer_node", "name of the QT trainer node (variants that train QT)")
    service_timeout_s: float = param(120.0, "seconds to wait for any one service answer", minimum=0.0)
    startup_timeout_s: float = param(30.0, "seconds to wait for the nodes' services at start", minimum=0.0)
    transport_probe_calls: int = param(
        200, "at the end, this many small service calls measure the ROS round trip for the time split "
        "(0 = skip)", minimum=0)


@dataclass(frozen=True)
class ComperNodeConfig(AgentRunConfig):
    """comper_node's own parameters (the learner's hyper-parameters are ComperConfig / DQNConfig)."""

    algorithm: str = param(
        "comper", "comper (Algorithm 7: RTM sampling, QT target) | comper_f (RTM sampling, DQN loss with a "
        "target network; chapter 7) | comper_m (QT target, sampling from TM; chapter 7) | dqn (baseline, "
        "Table 35: in-process replay, target network, no memory / QT nodes)", choices=COMPER_ALGORITHMS)
    env_id: str = param(
        "ALE/Freeway-v5", "task with discrete actions: an ALE game (ALE/<Game>-v5: Freeway, Asterix, Seaquest, "
        "...) or a gymnasium task with vector observations (CartPole-v1, Acrobot-v1, MountainCar-v0); "
        "embedded: given to the sim node; external: must match the running sim node")
    profile: str = param(
        "auto", "named set of learner defaults (core/config.py COMPER_PROFILES; -p name:=value still wins): "
        "thesis = Algorithm 7 and Tables 32-35; data_efficient = short Atari budgets (Adam, one update per step, "
        "4 frames, double DQN: Dopamine's atari_100k DER settings); atari_100k = data_efficient with 10-step targets "
        "and the QT-target gate's label test; classic_control = vector tasks; auto = atari_100k for ALE games, "
        "classic_control otherwise", thesis="thesis",
        choices=("auto", "thesis", "data_efficient", "atari_100k", "classic_control"))
    eval_every: int = param(
        -1, "agent steps between evaluations (eval_episodes greedy episodes on a separate environment; 0 = "
        "never); -1 = never for ALE games (the protocol reports training episodes), 5,000 for vector tasks",
        thesis="none for Atari (chapter 5 reports training episodes)", minimum=-1)
    eval_epsilon: float = param(0.0, "epsilon of the evaluated policy (0 = greedy; Dopamine evaluates Atari "
                                     "with 0.001)", minimum=0.0, maximum=1.0)
    progress_period_s: float = redefault(AgentRunConfig, "progress_period_s", 10.0)
    total_frames: int = param(
        100_000, "frame budget counting skipped frames (a vector task has one frame per step); the episode in "
        "progress when it is reached finishes", thesis="100,000 (chapter 5)", minimum=1)
    max_steps: int = param(0, "if > 0, also stop after this many agent steps, even mid-episode (tests, "
                              "smoke runs)", minimum=0)
    reduce_every: int = param(100, "agent steps between reductions + QT training (and whenever RTM is "
                                   "empty)", thesis="100 (Table 34, UTF)", minimum=1)
    reduce_batch: int = redefault(AgentRunConfig, "reduce_batch", 1_000)
    qt_wait_s: float = redefault(AgentRunConfig, "qt_wait_s", 5.0)
    reducer: str = param(
        "auto", "who reduces TM into RTM: qt_trainer (<qt_trainer_node>/reduce, trains QT) | memory "
        "(<memory_node>/reduce, newest label as prediction, no QT) | auto = memory for comper_f (it does "
        "not use QT), qt_trainer otherwise", choices=("auto", "qt_trainer", "memory"))
    restore_batch: bool = param(True, "re-store each updated batch with fresh labels (thesis 4.1.1; "
                                      "method.md 4)")
    store_every: int = param(4, "before learning starts / between updates: steps per store call (an update "
                                "and an episode end always flush)", minimum=1)
    stats_every: int = param(
        1_000, "agent steps between memory statistics records (identities, TM, RTM, set sizes) in "
        "metrics.jsonl (0 = only at the end)", minimum=0)
    checkpoint_every: int = param(5_000, "agent steps between checkpoints (0 = only the final one)", minimum=0)


@dataclass(frozen=True)
class ComcactNodeConfig(AgentRunConfig):
    """comcact_node's own parameters (the learner's hyper-parameters are ComcactConfig / DDPGConfig)."""

    algorithm: str = param(
        "comcact", "comcact (Algorithm 8: memory + QT step) or ddpg (baseline: plain uniform replay in this "
        "process, no QT step, no memory / QT trainer nodes)", choices=("comcact", "ddpg"))
    env_id: str = param(
        "InvertedPendulum-v4", "gymnasium task (continuous actions): InvertedPendulum-v4, Hopper-v4, "
        "Walker2d-v4, HalfCheetah-v4, InvertedDoublePendulum-v4, Pendulum-v1, ... (embedded: given to "
        "the sim node; external: must match the running sim node)")
    profile: str = param(
        "auto", "named set of learner defaults (core/config.py COMCACT_PROFILES; -p name:=value still wins): "
        "thesis = Algorithm 8 and appendix B as written (batch norm, a store and a reduction every step); plain = the "
        "defaults (no batch norm, store and reduce every 10); fresh_labels_gate = plain with restore_batch true, "
        "label_critic target and qt_step_gate true (value labels that follow the target critic, and the QT step only "
        "where QT is closer to the DDPG target than the critic); auto = fresh_labels_gate for comcact, plain for ddpg",
        thesis="thesis", choices=("auto", *COMCACT_PROFILES))
    total_steps: int = param(50_000, "agent (environment) steps of the run", thesis="50,000 (chapter 6)",
                             minimum=1)
    warmup_steps: int = param(
        0, "steps of uniformly random actions before the policy acts (sent in batches with step_many; no "
        "updates meanwhile); 0 = act with mu + noise from the first step",
        thesis="not given (Algorithm 8 acts with the policy from step 1)", minimum=0)
    store_every: int = param(
        10, "agent steps per memory store call (labels are computed when stored; an episode end and every "
        "reduction flush first, so RTM and the sampled batches are the same as with 1). ddpg: the replay "
        "gets the transitions in the same blocks (an update may not yet draw the newest <= 9 of them)",
        thesis="every step",
        minimum=1, deviation="10: the labels of up to 9 transitions are computed a few updates later, for a tenth "
        "of the store calls (docs/studies/comcact-speed.md); 1 = the thesis")
    reduce_every: int = param(
        10, "DDPG updates between reductions (a reduction also runs whenever RTM is empty)",
        thesis="every iteration (1; Algorithm 8 line 27-28)", minimum=1,
        deviation="10: a tenth of the reductions (docs/studies/comcact-speed.md); -p reduce_every:=1 is the "
        "thesis's cadence")
    reduce_batch: int = redefault(AgentRunConfig, "reduce_batch", 50_000)
    restore_batch: bool = param(
        False, "comcact: re-store each updated batch into TM with fresh value labels (computed after the "
        "update by label_critic's networks; sent with the next store call, in mode async every 20 updates marked "
        "relabel, which the memory's rate limiter does not count), so that a sampled transition's set "
        "collects a history of labels for QT to learn from, as in COMPER",
        thesis="no re-store in Algorithm 8 (each transition keeps the label of its store time)",
        deviation="true: labels that follow the critic; on continuous tasks almost every set has one member, so "
        "without it QT sees one label per set, computed when the transition arrived (method.md 6.4)")
    eval_every: int = param(5_000, "steps between evaluations (0 = never)", thesis="5,000 (chapter 6)",
                            minimum=0)
    checkpoint_every: int = param(
        0, "steps between checkpoints (0 = at every evaluation point); a final one is always written",
        minimum=0)
    mode: str = param(
        "lockstep", "lockstep = one environment step, then one update, in this node (Algorithm 8); async = actor "
        "nodes (actor_node: simulation + the current policy) store into the memory while this node samples and "
        "updates continuously, held to replay_ratio by the memory's rate limiter (docs/comcact.md, Async mode)",
        thesis="lockstep (Algorithm 8)", choices=("lockstep", "async"),
        deviation="async: updates run concurrently with acting, on networks up to policy_period_s old in the "
        "actors; the update-to-data ratio is held within the rate limiter's band instead of exactly 1")
    num_actors: int = param(
        1, "async: actor_node processes this node starts (embedded bring-up; distinct seeds seed + 1 + i); 0 = "
        "actors are started separately (ros2 run comper_agent actor_node)", minimum=0, maximum=64)
    policy_period_s: float = param(
        1.0, "async: seconds between publications of the current actor and critic on ~/policy", minimum=0.01)
    replay_ratio: float = param(
        1.0, "async: updates per environment step the memory's rate limiter holds (samples_per_insert = "
        "replay_ratio x batch_size, set on the embedded memory node)", thesis="1 (one update per step)",
        minimum=0.01)
    rate_buffer_steps: int = param(
        200, "async: how many environment steps acting may run ahead of (or behind) learning before one side "
        "waits (the rate limiter's error buffer, in steps)", minimum=1)


@dataclass(frozen=True)
class ActorNodeConfig:
    """actor_node's parameters: an environment and the learner's current policy, storing into the memory
    (comcact_node mode:=async). The networks' shape and noise come with the policy message."""

    env_id: str = param("InvertedPendulum-v4", "gymnasium task (continuous actions); must be the learner's")
    seed: int = param(0, "seed of the environment's resets and of the exploration noise", minimum=0)
    actor_id: int = param(0, "this actor's number (episode ids are actor_id x 1e9 + episode)", minimum=0,
                          maximum=1000)
    memory_node: str = param("memory_node", "name (or /namespace/name) of the memory node to store into")
    policy_topic: str = param("/comcact_node/policy", "the learner's PolicyWeights topic")
    total_steps: int = param(0, "environment steps of this actor (0 = until the learner's final policy message "
                                "or Ctrl-C)", minimum=0)
    store_every: int = param(10, "steps per store call (an episode end flushes first)", minimum=1)
    policy: str = param("learner", "learner = act with the learner's policy from policy_topic; random = uniform "
                        "random actions, label 0, no learner needed (throughput measurements, warm-up data)",
                        choices=("learner", "random"))
    episode_end: str = param("standard", "episode end rule: standard, truncation_only, termination_only",
                             choices=EPISODE_END_RULES)
    startup_timeout_s: float = param(60.0, "seconds to wait for the memory node and the first policy", minimum=0.0)
    service_timeout_s: float = param(20.0, "seconds per memory service answer (a store without an answer is sent "
                                           "again, up to 3 times)", minimum=0.0)
    rate_limit_timeout_s: float = param(
        600.0, "seconds a store may wait for the learner (the memory's rate limiter) before the actor gives up",
        minimum=0.0)


@dataclass(frozen=True)
class QtTrainerNodeConfig:
    """qt_trainer_node's own parameters (QT's hyper-parameters: QTConfig or ComcactQTConfig, by
    architecture)."""

    architecture: str = param(
        "comcact", "QT layout and defaults: comcact = appendix B (LSTM 64-64, dense 32), comper = Table 37 "
        "(LSTM 64-32-32, dense 18)", choices=("comcact", "comper"))
    memory_node: str = param("memory_node", "name (or /namespace/name) of the memory node whose reduce_begin / "
                                            "reduce_commit services are called")
    reduce_batch: int = param(0, "sets popped from TM per reduction; 0 = the memory node's reduce_batch",
                              thesis="50,000 for COMCACT (appendix B), 1,000 for COMPER (Table 34)", minimum=0)
    period_s: float = param(0.0, "if > 0, also reduce on a timer every period_s seconds (0 = only on ~/reduce "
                                 "requests)", minimum=0.0)
    call_timeout_s: float = param(60.0, "seconds to wait for each memory service answer", minimum=0.0)
    num_threads: int = param(0, "torch intra-op threads set at start when > 0 (standalone: default 1 when 0)",
                             minimum=0)
