"""sim_node: the simulation bridge as a ROS 2 node (thin: translation between messages and the core).

    ros2 run comper_sim sim_node --ros-args -p env_id:=ALE/Freeway-v5 -p frame_stack:=4
    ros2 run comper_sim sim_node --ros-args --params-file src/comper_sim/config/sim.yaml

Services (private, relative to the node): ``~/reset`` (comper_msgs/srv/Reset), ``~/step`` (Step),
``~/step_many`` (StepMany: K actions in one round trip, the K transitions back as one
TransitionBatch), ``~/info`` (EnvInfo). Topic: ``~/episodes`` (comper_msgs/msg/EpisodeSummary,
source "sim"), one message per finished episode. Parameters: :class:`comper_sim.core.SimConfig`.

A refused request answers ``success=false`` with the reason in ``message`` and changes nothing;
the node keeps serving. All the logic lives in :mod:`comper_sim.core`.
"""
from __future__ import annotations

import json
import sys

import numpy as np
import rclpy
from rclpy.node import Node

from comper_msgs.msg import Array, EpisodeSummary
from comper_msgs.srv import EnvInfo, Reset, Step, StepMany
from comper_msgs_py.arrays import TransitionError
from comper_msgs_py.convert import array_to_numpy, numpy_to_array, numpy_to_seq, transitions_to_batch
from comper_msgs_py.qos import RECORDED_QOS, SERVICE_QOS
from comper_msgs_py.ros_main import serve_node
from comper_msgs_py.ros_params import declare_config

from .core import EpisodeRecord, SimBridge, SimConfig, SimError

__all__ = ["SimNode", "main", "EPISODES_QOS"]

# Episode summaries are few (one per episode) and every one counts for the learning curves: the
# recorded topics' QoS (comper_msgs_py.qos says why reliable, keep-last 100, volatile)
EPISODES_QOS = RECORDED_QOS

_REFUSED = (SimError, TransitionError)


class SimNode(Node):
    """The simulation bridge node. ``node_kwargs`` go to rclpy's Node (context,
    parameter_overrides, namespace, ...) so other nodes can embed it in their process.

    Raises at construction when the environment cannot be made (unknown env id, bad parameter).
    """

    def __init__(self, node_name: str = "sim_node", **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        try:
            self.config: SimConfig = declare_config(self, SimConfig)
            self.bridge = SimBridge(self.config)
        except Exception:
            self.destroy_node()
            raise
        self._env_id = self.config.env_id
        self._episodes_pub = self.create_publisher(EpisodeSummary, "~/episodes", EPISODES_QOS)
        self.create_service(Reset, "~/reset", self._on_reset, qos_profile=SERVICE_QOS)
        self.create_service(Step, "~/step", self._on_step, qos_profile=SERVICE_QOS)
        self.create_service(StepMany, "~/step_many", self._on_step_many, qos_profile=SERVICE_QOS)
        self.create_service(EnvInfo, "~/info", self._on_info, qos_profile=SERVICE_QOS)
        info = self.bridge.info()
        actions = (f"{info.num_actions} discrete actions" if info.discrete
                   else f"actions {list(info.action_shape)} in [{info.action_low.min():g}, {info.action_high.max():g}]")
        self.get_logger().info(
            f"serving {info.env_id}: observation {list(info.observation_shape)} {info.observation_dtype}, "
            f"{actions}, frame_skip {info.frame_skip}, max_episode_steps {info.max_episode_steps}, "
            f"episode_end {info.episode_end}, seed {self.config.seed}")

    # --- helpers ------------------------------------------------------------------------------
    def _refuse(self, response, what: str, exc: Exception):
        if isinstance(exc, _REFUSED):
            self.get_logger().warning(f"{what} refused: {exc}")
            response.message = str(exc)
        else:  # a bug or an environment failure: report it, keep serving
            self.get_logger().error(f"{what} failed: {type(exc).__name__}: {exc}")
            response.message = f"internal error: {type(exc).__name__}: {exc}"
        response.success = False
        return response

    def _publish_episode(self, rec: EpisodeRecord) -> None:
        msg = EpisodeSummary()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.run_id = self.config.run_id
        msg.env_id = self._env_id
        msg.source = "sim"
        msg.episode_id = rec.episode_id
        msg.episode_return = float(rec.episode_return)
        msg.length = rec.length
        msg.frames = rec.frames
        msg.terminated = rec.terminated
        msg.truncated = rec.truncated
        msg.global_step = rec.global_step
        msg.global_frames = rec.global_frames
        msg.wall_time_s = float(rec.wall_time_s)
        self._episodes_pub.publish(msg)
        self.get_logger().debug(f"episode {rec.episode_id} ended: return {rec.episode_return:g}, "
                                f"{rec.length} steps, {rec.frames} frames")

    # --- services -----------------------------------------------------------------------------
    def _on_reset(self, request: Reset.Request, response: Reset.Response):
        try:
            obs, episode_id = self.bridge.reset(request.seed if request.seed >= 0 else None)
        except Exception as exc:
            return self._refuse(response, "reset", exc)
        numpy_to_array(obs, response.observation)
        response.episode_id = episode_id
        response.success = True
        return response

    def _on_step(self, request: Step.Request, response: Step.Response):
        try:
            result = self.bridge.step(array_to_numpy(request.action))
        except Exception as exc:
            return self._refuse(response, "step", exc)
        numpy_to_array(result.observation, response.observation)
        response.reward = float(result.reward)
        response.terminated = result.terminated
        response.truncated = result.truncated
        response.episode_id = result.episode_id
        response.episode_step = result.episode_step
        response.frames = result.frames
        response.success = True
        if result.episode is not None:
            self._publish_episode(result.episode)
        return response

    def _on_step_many(self, request: StepMany.Request, response: StepMany.Response):
        try:
            result = self.bridge.step_many(array_to_numpy(request.actions), autoreset=request.autoreset)
        except Exception as exc:
            return self._refuse(response, "step_many", exc)
        transitions_to_batch(result.transitions, response.transitions)
        response.transitions.header.stamp = self.get_clock().now().to_msg()
        numpy_to_array(result.observation, response.observation)
        response.episodes_ended = result.episodes_ended
        response.success = True
        for rec in result.episodes:
            self._publish_episode(rec)
        return response

    def _on_info(self, request: EnvInfo.Request, response: EnvInfo.Response):
        info = self.bridge.info()
        response.env_id = info.env_id
        response.observation_shape = [int(d) for d in info.observation_shape]
        response.observation_dtype = Array.DTYPE_UINT8 if info.observation_dtype == np.uint8 else Array.DTYPE_FLOAT32
        response.discrete = info.discrete
        response.num_actions = info.num_actions
        response.action_shape = [int(d) for d in info.action_shape]
        response.action_low = numpy_to_seq(info.action_low, np.float32)
        response.action_high = numpy_to_seq(info.action_high, np.float32)
        response.max_episode_steps = int(info.max_episode_steps)
        response.frame_skip = int(info.frame_skip)
        response.episode_end = info.episode_end
        response.spec_json = json.dumps(info.spec, sort_keys=True)
        return response

    def destroy_node(self):
        bridge = getattr(self, "bridge", None)
        if bridge is not None:
            bridge.close()
            self.bridge = None
        return super().destroy_node()


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_sim sim_node``: 0 on Ctrl-C, 1 when it cannot start."""
    return serve_node(SimNode, "sim_node", args)


if __name__ == "__main__":
    sys.exit(main())
