"""SimClient: numpy in, numpy out access to a running ``sim_node`` (``<sim>/reset``, ``step``,
``step_many``, ``info``), for the suite's learners and any other rclpy learner.

The node must be spun by an executor in another thread, or use ``SimClient.standalone(sim_node)``
(see :mod:`comper_msgs_py.service_client`, which also defines the errors)::

    with SimClient.standalone("sim_node") as sim:
        sim.wait_for_service(10.0)
        obs = sim.reset(seed=0)
        r = sim.step(np.array([0.1, -0.2], np.float32))
        r.observation, r.reward, r.terminated, r.truncated
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comper_msgs.srv import EnvInfo, Reset, Step, StepMany
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import array_to_numpy, batch_to_transitions, numpy_to_array
from comper_msgs_py.service_client import ServiceClient

__all__ = ["SimClient", "StepReply", "StepManyReply"]


@dataclass
class StepReply:
    observation: np.ndarray   # s_{t+1}, a copy (dtype as asked, else the sim's)
    reward: float
    terminated: bool
    truncated: bool
    episode_id: int
    episode_step: int         # agent steps in this episode so far
    frames: int               # emulator frames in this episode so far (counts skipped frames)


@dataclass
class StepManyReply:
    transitions: Transitions  # [<= K], value_labels empty
    observation: np.ndarray   # the current observation (after a reset when autoreset ended an episode)
    episodes_ended: int


def _obs(array_msg, dtype) -> np.ndarray:
    return np.array(array_to_numpy(array_msg), dtype=dtype)


class SimClient(ServiceClient):
    """Client of one sim node. node: an rclpy node spun by an executor in another thread; sim_node:
    the sim node's name or fully qualified name; timeout: default seconds per call."""

    NODE_NAME = "sim_client"

    def __init__(self, node, sim_node: str = "sim_node", *, timeout: float = 30.0, callback_group=None):
        super().__init__(node, sim_node, timeout=timeout, callback_group=callback_group)
        self._reset = self._make(Reset, "reset")
        self._step = self._make(Step, "step")
        self._step_many = self._make(StepMany, "step_many")
        self._info = self._make(EnvInfo, "info")

    def step_client(self):
        """The rclpy client of ``<sim>/step`` (for :func:`wait_for_services`)."""
        return self._step

    #: seconds after which an unanswered ``info`` request is sent again (a read: repeating it is harmless).
    #: A learner's first call is ``info``, and a new client's first answer can be lost while discovery
    #: completes (docs/memory-service.md, "Lost answers and re-sends"); without it that costs the whole timeout
    INFO_RESEND_S = 2.0

    def info(self, *, timeout: float | None = None) -> EnvInfo.Response:
        """The task's description (id, spaces, frame skip, episode end rule, protocol as JSON); sent again
        every ``INFO_RESEND_S`` until answered or ``timeout`` is over."""
        return self._call(self._info, EnvInfo.Request(), timeout, check=False, resend_s=self.INFO_RESEND_S)

    def reset(self, seed: int = -1, *, dtype=None, timeout: float | None = None) -> np.ndarray:
        """Start an episode; seed < 0 continues the node's random stream. Returns s_0 (a copy)."""
        return _obs(self._call(self._reset, Reset.Request(seed=int(seed)), timeout).observation, dtype)

    def step(self, action, *, dtype=None, timeout: float | None = None) -> StepReply:
        """One agent step (the sim's frame skip inside). action: float32 [action_dim], or the index."""
        req = Step.Request()
        numpy_to_array(np.asarray(action, np.float32), req.action)
        r = self._call(self._step, req, timeout)
        return StepReply(_obs(r.observation, dtype), float(r.reward), bool(r.terminated), bool(r.truncated),
                         int(r.episode_id), int(r.episode_step), int(r.frames))

    def step_many(self, actions, *, autoreset: bool = True, dtype=None,
                  timeout: float | None = None) -> StepManyReply:
        """K steps in one call (actions [K, action_dim] or [K]); stops early at an episode end unless
        autoreset."""
        req = StepMany.Request(autoreset=bool(autoreset))
        numpy_to_array(np.asarray(actions, np.float32), req.actions)
        r = self._call(self._step_many, req, timeout)
        return StepManyReply(batch_to_transitions(r.transitions), _obs(r.observation, dtype), int(r.episodes_ended))
