"""A learner node's episodes as the outside sees them.

:class:`LearnerTopics` - ``~/episodes``, ``~/evaluations`` and ``~/transitions`` (the recording
contract, docs/recording.md): one place that builds their messages and applies the recording
link's flow control.

:class:`TrainingEpisodes` - the training environment as the learner steps it (the sim node through
:class:`~comper_sim.client.SimClient`) and its episodes: the one in progress (return, length, the
transitions stored from it) and how many have ended; each one ends by going out on the topics and
into the run's logs.
"""
from __future__ import annotations

import numpy as np

from comper_msgs.msg import EpisodeSummary, EvaluationResult, TransitionBatch
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import transitions_to_batch
from comper_msgs_py.qos import RECORDED_QOS, wait_acknowledged
from comper_sim.core import episode_over

from comper_agent.core.memory_schedule import rows_to_transitions

__all__ = ["LearnerTopics", "TrainingEpisodes", "SUMMARY_QOS"]

#: QoS of ~/episodes, ~/evaluations, ~/transitions (the recording contract, docs/recording.md)
SUMMARY_QOS = RECORDED_QOS


class LearnerTopics:
    """node: the learner node (it owns the publishers); run_id, env_id: written into every message;
    publish_transitions: the node's parameter; timers: its run_io.PhaseTimers; stop_event: ends a
    wait for the recorder. ``recording`` is the RecordingLink once the node has brought it up
    (record:=true), else None."""

    def __init__(self, node, run_id: str, env_id: str, publish_transitions: bool, timers, stop_event):
        self.node, self.run_id, self.env_id = node, run_id, env_id
        self.publish_transitions, self.timers, self.stop_event = publish_transitions, timers, stop_event
        self.episodes = node.create_publisher(EpisodeSummary, "~/episodes", SUMMARY_QOS)
        self.evaluations = node.create_publisher(EvaluationResult, "~/evaluations", SUMMARY_QOS)
        self.transitions = node.create_publisher(TransitionBatch, "~/transitions", SUMMARY_QOS)
        self.recording = None

    def _stamp(self):
        return self.node.get_clock().now().to_msg()

    def hand_over(self, timeout_s: float) -> bool:
        """Before the node is destroyed: waits, at most ``timeout_s`` in all, until every matched
        reliable subscriber of the three topics has acknowledged what was published (the last
        evaluation and the final summary go out just before a finished run ends; destroying the
        publisher first would drop whatever is still unacknowledged). True when all were."""
        return wait_acknowledged((self.evaluations, self.episodes, self.transitions), timeout_s)

    def transitions_wanted(self) -> bool:
        """Whether a training episode's transitions go out: publish_transitions and someone records
        or subscribes."""
        return self.publish_transitions and (self.recording is not None
                                             or self.transitions.get_subscription_count() > 0)

    def train_episode(self, parts: list[Transitions], **summary) -> None:
        """A finished training episode: its stored transitions (`parts`, when wanted) on
        ~/transitions, then its EpisodeSummary (`summary`: the message's fields) on ~/episodes, with
        one stamp. While recording, first waits as long as record_window episodes are unwritten."""
        stamp = self._stamp()
        send_transitions = bool(parts) and self.transitions_wanted()
        if self.recording is not None:
            topics = [self.episodes.topic_name] + ([self.transitions.topic_name] if send_transitions else [])
            waited = self.recording.wait_window(topics, self.stop_event)
            if waited > 0:
                self.timers.add("record_wait", waited)
        with self.timers("publish"):
            if send_transitions:
                bm = transitions_to_batch(parts[0] if len(parts) == 1 else Transitions.concatenate(parts))
                bm.header.stamp = stamp
                self.transitions.publish(bm)
                if self.recording is not None:
                    self.recording.sent(self.transitions.topic_name)
            msg = EpisodeSummary(run_id=self.run_id, env_id=self.env_id, source="train", **summary)
            msg.header.stamp = stamp
            self.episodes.publish(msg)
            if self.recording is not None:
                self.recording.sent(self.episodes.topic_name)

    def eval_episode(self, **summary) -> None:
        """One evaluation episode's EpisodeSummary (source eval) on ~/episodes."""
        msg = EpisodeSummary(run_id=self.run_id, env_id=self.env_id, source="eval", **summary)
        msg.header.stamp = self._stamp()
        self.episodes.publish(msg)

    def evaluation(self, algorithm: str, **fields) -> None:
        """An EvaluationResult on ~/evaluations."""
        msg = EvaluationResult(run_id=self.run_id, algorithm=algorithm, env_id=self.env_id, **fields)
        msg.header.stamp = self._stamp()
        self.evaluations.publish(msg)


class TrainingEpisodes:
    """sim: the SimClient of the training environment; topics: LearnerTopics; outputs: the node's
    AgentRun (logs, wall clock); timers: run_io.PhaseTimers; obs_dtype: observations' dtype.

    ``ret``, ``length``, ``parts``: the episode in progress (its return, steps and the transitions
    stored from it, published with it); ``count``: episodes ended in this run (resumes included)."""

    def __init__(self, sim, topics: LearnerTopics, outputs, timers, obs_dtype):
        self.sim, self.topics, self.outputs, self.timers, self.obs_dtype = sim, topics, outputs, timers, obs_dtype
        self.count = 0
        self.begin()

    def begin(self) -> None:
        """A new episode in progress (after a reset, or an automatic one inside step_many)."""
        self.ret, self.length = 0.0, 0
        self.parts: list[Transitions] = []
        self.rows: list | None = [] if self.topics.transitions_wanted() else None    # add_row's, while wanted

    def reset(self) -> np.ndarray:
        """``<sim>/reset`` (the sim's own seed sequence); the first observation."""
        with self.timers("sim"):
            obs = self.sim.reset(-1, dtype=self.obs_dtype)
        self.begin()
        return obs

    def step(self, action: np.ndarray):
        """``<sim>/step``; adds the reward and the step to the episode. Returns (StepReply, next obs)."""
        with self.timers("sim"):
            r = self.sim.step(action, dtype=self.obs_dtype)
        self.add(r.reward)
        return r, r.observation

    def step_many(self, actions: np.ndarray, *, rule: str, step: int, run_id: str):
        """``<sim>/step_many`` with automatic resets (warm-up chunks of random actions; adds nothing to the
        episode, the learner walks the steps). Returns (the transitions as float32 ``Transitions``, episode ids
        counted from ``count``, steps from the learner's `step`; which of them end an episode by `rule`; the
        observation after the last)."""
        with self.timers("sim"):
            r = self.sim.step_many(actions, autoreset=True, dtype=np.float32)
        t = r.transitions
        over = np.array([episode_over(rule, a, b) for a, b in zip(t.terminated, t.truncated)])
        ends_before = np.concatenate([[0], np.cumsum(over)[:-1]]).astype(np.uint64)
        t = Transitions(states=np.array(t.states, np.float32), actions=np.array(t.actions, np.float32),
                        rewards=np.array(t.rewards, np.float32), next_states=np.array(t.next_states, np.float32),
                        terminated=np.array(t.terminated), truncated=np.array(t.truncated),
                        episode_ids=self.count + ends_before,
                        steps=np.arange(step, step + len(t), dtype=np.uint64), run_id=run_id)
        return t, over, r.observation

    def add_row(self, row) -> None:
        """A step the learner keeps one at a time (DQN's local replay; a ``memory_schedule.Row``): published with
        the episode on ~/transitions when someone subscribed or recorded at its start."""
        if self.rows is not None:
            self.rows.append(row)

    def add(self, reward: float) -> None:
        """One step of the episode in progress that the learner took itself (warm-up chunks)."""
        self.ret += reward
        self.length += 1

    def end(self, terminated: bool, truncated: bool, *, step: int, ep_frames: int | None = None,
            global_frames: int | None = None, x: int | None = None, **fields) -> None:
        """Count the episode, publish it (transitions, then summary) and log it at the learner's
        `step`. `ep_frames`, `global_frames`: emulator frames of the episode and of the run (default:
        its length and `step`, one frame per step); `x`: its TensorBoard step (default `step`);
        `fields` go to its metrics record. ``ret`` and ``length`` stay readable until the next
        :meth:`begin`."""
        ep_frames = self.length if ep_frames is None else ep_frames
        global_frames = step if global_frames is None else global_frames
        x = step if x is None else x
        if self.rows:
            self.parts.append(rows_to_transitions(self.rows, self.count, self.topics.run_id))
            self.rows = []
        self.count += 1
        out = self.outputs
        out.progress.episode(self.ret)
        parts, self.parts = self.parts, []
        self.topics.train_episode(parts, episode_id=self.count - 1, episode_return=float(self.ret),
                                  length=int(self.length), frames=int(ep_frames), terminated=bool(terminated),
                                  truncated=bool(truncated), global_step=int(step),
                                  global_frames=int(global_frames), wall_time_s=float(out.wall_time()))
        out.metrics.write("episode", source="train", step=step, episode=self.count - 1, ret=self.ret,
                          length=self.length, terminated=terminated, truncated=truncated,
                          wall_time_s=out.wall_time(), **fields)
        out.scalars.scalar("train/episode_return", self.ret, x)
