"""The learner's actor and critic as a comper_msgs/PolicyWeights message, and back.

comcact_node (mode:=async) publishes its current networks on ``~/policy`` every policy_period_s;
actor_node rebuilds the same networks from the message's config and loads the weights. The tensors
travel as named float32 Arrays (comper_msgs_py.convert), never as pickles.
"""
from __future__ import annotations

import json

import numpy as np
import torch
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from comper_msgs.msg import PolicyWeights
from comper_msgs_py.convert import array_to_numpy, numpy_to_array
from comper_msgs_py.params import config_from_dict, config_to_dict

__all__ = ["POLICY_QOS", "PolicyPublisher", "policy_to_msg", "load_policy_msg", "config_of_policy"]

#: reliable, transient local, depth 1: an actor that starts late gets the latest networks at once
POLICY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)

_PARTS = ("actor", "critic")
_TARGET_PARTS = ("actor_target", "critic_target")


def _parts_of(learner) -> tuple[str, ...]:
    """The networks a message carries: the online actor and critic, and with label_critic target also
    the target networks, which then give the actors' labels (the learner's label rule)."""
    return _PARTS + (_TARGET_PARTS if learner.config.label_critic == "target" else ())


def policy_to_msg(learner, *, version: int, env_steps: int, final: bool = False) -> PolicyWeights:
    """The learner's online actor and critic (ComcactLearner) as a PolicyWeights message, and its
    target networks too when it labels with them (label_critic target)."""
    msg = PolicyWeights(version=int(version), env_steps=int(env_steps), final=bool(final))
    cfg = {k: (list(v) if isinstance(v, tuple) else v) for k, v in config_to_dict(learner.config).items()}
    msg.config_json = json.dumps(cfg, sort_keys=True)
    names, tensors = [], []
    for part in _parts_of(learner):
        for k, v in getattr(learner, part).state_dict().items():
            names.append(f"{part}.{k}")
            tensors.append(numpy_to_array(v.detach().cpu().numpy().astype(np.float32)))
    msg.tensor_names = names
    msg.tensors = tensors
    return msg


def config_of_policy(msg: PolicyWeights, config_cls):
    """The learner's config carried by the message (to build networks of the same shape)."""
    return config_from_dict(config_cls, json.loads(msg.config_json), ignore_unknown=True)


def load_policy_msg(learner, msg: PolicyWeights) -> None:
    """Load the message's actor and critic into `learner` (same architecture; ValueError if not).
    The target networks get the message's target networks when it carries them (label_critic target),
    else the same weights as the online ones (an actor uses them only for target labels)."""
    states = {p: {} for p in _PARTS + _TARGET_PARTS}
    for name, arr in zip(msg.tensor_names, msg.tensors):
        part, _, key = name.partition(".")
        if part not in states:
            raise ValueError(f"policy message: unknown tensor {name!r}")
        states[part][key] = np.array(array_to_numpy(arr), copy=True)
    for part in _PARTS + tuple(p for p in _TARGET_PARTS if states[p]):
        net = getattr(learner, part)
        own = net.state_dict()
        if set(own) != set(states[part]):
            raise ValueError(f"policy message: the {part}'s tensors differ from this learner's "
                             f"({sorted(set(own) ^ set(states[part]))[:3]} ...)")
        net.load_state_dict({k: torch.as_tensor(v, dtype=own[k].dtype).reshape(own[k].shape)
                             for k, v in states[part].items()})
        if part in _PARTS and not states[f"{part}_target"]:
            getattr(learner, f"{part}_target").load_state_dict(net.state_dict())


class PolicyPublisher:
    """Publishes PolicyWeights on `topic` from a node in a context (a DDS participant) of its own.

    Why its own participant: Fast DDS's shared-memory transport allocates every outgoing sample of
    a participant from one segment. A slow local reader of these ~1 MB messages (a `ros2 topic echo`,
    a test that spins slowly) holds buffers of that segment, and once it is full the participant's
    other samples are lost too: with the policy published from the learner's own participant, the
    memory node's service answers to the actors (embedded in the same process) stopped arriving and a
    store waited for ever (reproduced with one slowly spinning subscriber; gone with UDP-only
    transport). From a participant of its own, a slow reader can only delay the policy itself."""

    def __init__(self, topic: str, node_name: str):
        import rclpy
        from rclpy.node import Node
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        try:
            self.node = Node(node_name, context=self.context, start_parameter_services=False)
            self.pub = self.node.create_publisher(PolicyWeights, topic, POLICY_QOS)
        except BaseException:
            self.context.try_shutdown()
            raise
        self.topic_name = self.pub.topic_name
        self.published = 0

    def send(self, learner, env_steps: int, final: bool = False) -> None:
        """The learner's current actor and critic (version: its update count), stamped and published."""
        msg = policy_to_msg(learner, version=learner.updates, env_steps=env_steps, final=final)
        msg.header.stamp = self.stamp()
        self.publish(msg)
        self.published += 1

    def publish(self, msg: PolicyWeights) -> None:
        self.pub.publish(msg)

    def stamp(self):
        return self.node.get_clock().now().to_msg()

    def close(self) -> None:
        try:
            self.node.destroy_node()
        finally:
            self.context.try_shutdown()
