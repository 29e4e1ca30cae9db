"""qt_trainer_node: trains the Q-target network QT and drives the memory's two-phase reduction.

    ros2 run comper_agent qt_trainer_node --ros-args -p memory_node:=memory_node
    ros2 run comper_agent qt_trainer_node --ros-args --params-file src/comper_agent/config/qt_trainer.yaml

Service ``~/reduce`` (comper_msgs/srv/Reduce): pop up to ``reduce_batch`` sets from TM
(``<memory_node>/reduce_begin``), train QT on them (``qt_epochs`` passes), predict one value per
set, upsert RTM (``<memory_node>/reduce_commit``), publish the new model, answer. The nested calls
run in a reentrant callback group on a multi-threaded executor (docs/architecture.md).

Topic ``~/qt_model`` (comper_msgs/msg/QTModel; reliable, transient local, depth 1): the weights
as named Arrays, the scalers and the version, published whenever the model changes, so a learner
that starts late still gets the current model. :func:`qt_to_msg` / :func:`msg_to_qt` convert.

Optional: ``period_s`` > 0 also reduces on a timer (0 = only on request).
Keys: ``comper_memory.core.transition_keys`` (the memory's own key builder).
"""
from __future__ import annotations

import json
import sys
import threading
import time

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from comper_msgs.msg import QTModel as QTModelMsg
from comper_memory.client import MemoryClient, MemoryServiceError
from comper_memory.core.results import LEASE_GONE
from comper_msgs.srv import Reduce
from comper_msgs_py.convert import array_to_numpy, numpy_to_array, numpy_to_seq, seq_to_numpy
from comper_msgs_py.qos import SERVICE_QOS
from comper_msgs_py.ros_main import serve_node
from comper_msgs_py.ros_params import declare_config
from comper_msgs_py.service_client import ServiceError
from comper_agent.core.config import QT_CONFIGS
from comper_agent.nodes.node_config import QtTrainerNodeConfig

__all__ = ["QtTrainerNode", "QT_MODEL_QOS", "qt_to_msg", "msg_to_qt", "main"]

QT_MODEL_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)


# ------------------------------------------------------------------------------- conversion
def qt_to_msg(arrays: dict, out: QTModelMsg | None = None) -> QTModelMsg:
    """``QTModel.to_arrays()`` -> comper_msgs/QTModel (tensors as named float32 Arrays)."""
    msg = out if out is not None else QTModelMsg()
    msg.version = int(arrays["version"])
    msg.architecture = str(arrays["architecture"])
    msg.config_json = json.dumps(arrays["config"], sort_keys=True)
    msg.key_size = int(arrays["key_size"])
    msg.sequence_length = int(arrays["sequence_length"])
    names = list(arrays["tensors"].keys())
    msg.tensor_names = names
    msg.tensors = [numpy_to_array(np.asarray(arrays["tensors"][n], np.float32)) for n in names]
    msg.input_mean = numpy_to_seq(arrays["input_mean"], np.float32)
    msg.input_std = numpy_to_seq(arrays["input_std"], np.float32)
    msg.label_mean = float(arrays["label_mean"])
    msg.label_std = float(arrays["label_std"])
    loss = float(arrays["train_loss"])
    msg.train_loss = loss if np.isfinite(loss) else float("nan")
    msg.train_sets = int(arrays["train_sets"])
    return msg


def msg_to_qt(msg: QTModelMsg, device: str | None = "cpu"):
    """comper_msgs/QTModel -> a predicting :class:`comper_agent.core.qt.QTModel`."""
    from comper_agent.core.qt import QTModel
    tensors = {n: np.array(array_to_numpy(a), dtype=np.float32) for n, a in zip(msg.tensor_names, msg.tensors)}
    return QTModel.from_arrays(
        architecture=msg.architecture, config=json.loads(msg.config_json), key_size=int(msg.key_size),
        sequence_length=int(msg.sequence_length), tensors=tensors,
        input_mean=seq_to_numpy(msg.input_mean, np.float32).copy(),
        input_std=seq_to_numpy(msg.input_std, np.float32).copy(),
        label_mean=float(msg.label_mean), label_std=float(msg.label_std), version=int(msg.version),
        train_loss=float(msg.train_loss), train_sets=int(msg.train_sets), device=device)


# ------------------------------------------------------------------------------- node
class QtTrainerNode(Node):
    """QT trainer. ``node_kwargs`` go to rclpy's Node (context, parameter_overrides, ...), so a
    learner can embed it in its own process."""

    def __init__(self, node_name: str = "qt_trainer_node", **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        self.p = p = declare_config(self, QtTrainerNodeConfig)
        arch = p.architecture
        self.qt_config = declare_config(self, QT_CONFIGS[arch], overrides={"qt_architecture": arch})
        if self.qt_config.qt_architecture != arch:
            raise ValueError(f"qt_architecture:={self.qt_config.qt_architecture} contradicts "
                             f"architecture:={arch}; set architecture only")
        self.memory_name = p.memory_node.strip("/")

        from comper_memory.core import transition_keys

        from comper_agent.core.qt import QTModel
        self.key_fn = transition_keys
        self.qt = QTModel(self.qt_config)
        self._lock = threading.Lock()      # one reduction at a time
        self.reductions = 0
        self.last_duration_s = 0.0

        self._group = ReentrantCallbackGroup()
        self.memory = MemoryClient(self, f"/{self.memory_name}", timeout=p.call_timeout_s,
                                   callback_group=self._group)
        self._pub = self.create_publisher(QTModelMsg, "~/qt_model", QT_MODEL_QOS)
        self.create_service(Reduce, "~/reduce", self._on_reduce, qos_profile=SERVICE_QOS, callback_group=self._group)
        if p.period_s > 0:
            self.create_timer(p.period_s, self._on_timer, callback_group=MutuallyExclusiveCallbackGroup())
        c = self.qt_config
        self.get_logger().info(
            f"QT trainer ready: architecture {arch} (LSTM {list(c.qt_lstm_units)}, dense {c.qt_dense_units}, "
            f"{c.qt_output_activation} output), RMSProp lr {c.qt_lr:g}, batch {c.qt_batch_size}, "
            f"epochs {c.qt_epochs}; memory /{self.memory_name}; reduce_batch "
            f"{p.reduce_batch or 'memory default'}; timer {'off' if p.period_s <= 0 else f'{p.period_s:g} s'}")

    def make_executor(self, context=None):
        """Multi-threaded: the reduce service waits on nested calls to the memory node."""
        return MultiThreadedExecutor(num_threads=4, context=context)

    # --------------------------------------------------------------------------- state
    def state_dict(self) -> dict:
        return {"qt": self.qt.state_dict(), "reductions": self.reductions}

    def load_state_dict(self, state: dict) -> None:
        with self._lock:
            self.qt.load_state_dict(state["qt"])
            self.reductions = int(state.get("reductions", 0))
        if self.qt.net is not None:
            self.publish_model()

    def publish_model(self) -> None:
        if self.qt.net is None:
            return
        msg = qt_to_msg(self.qt.to_arrays())
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub.publish(msg)

    # --------------------------------------------------------------------------- reduction
    def reduce(self, max_sets: int = 0, epochs: int = 0) -> dict:
        """One whole reduction; returns the Reduce response fields. Raises ServiceError."""
        from comper_agent.core.qt import reduction_predictor
        with self._lock:
            t0 = time.monotonic()
            if not self.memory.ready() and not self.memory.wait_for_service(5.0):
                raise ServiceError(f"/{self.memory_name}/reduce_begin is not available")
            lease = self.memory.reduce_begin(int(max_sets or self.p.reduce_batch))
            t_lease = time.monotonic()
            m = len(lease)
            loss = float("nan")
            if m == 0:
                # nothing in TM: commit the empty lease so the memory can forget it
                try:
                    rtm_size = self.memory.reduce_commit(lease.reduction_id, [], []).rtm_size
                except MemoryServiceError:
                    rtm_size = int(self.memory.stats()["rtm_size"])
                return {"sets_reduced": 0, "rtm_size": rtm_size, "qt_version": self.qt.version,
                        "qt_loss": loss, "duration_s": time.monotonic() - t0,
                        "message": "TM is empty: nothing to reduce"}
            predict = reduction_predictor(self.qt, epochs=int(epochs) or None, key_fn=self.key_fn)
            preds = np.asarray(predict(lease), np.float32)
            t_qt = time.monotonic()
            loss = float(self.qt.train_loss)
            try:
                commit = self.memory.reduce_commit(lease.reduction_id, lease.identity_ids, preds)
            except MemoryServiceError as exc:
                if LEASE_GONE not in str(exc):
                    raise
                return self._not_committed(m, loss, t0, exc)
            t_commit = time.monotonic()
            self.reductions += 1
            self.publish_model()
            t_end = time.monotonic()
            self.last_duration_s = t_end - t0
            # where a round's time goes: the lease's transfer, QT's keys + fit + predict, the commit, publishing
            return {"sets_reduced": commit.committed, "rtm_size": commit.rtm_size,
                    "qt_version": int(self.qt.version), "qt_loss": loss, "duration_s": self.last_duration_s,
                    "message": f"reduced {m} sets: lease {t_lease - t0:.2f} s, QT {t_qt - t_lease:.2f} s, "
                               f"commit {t_commit - t_qt:.2f} s, model {t_end - t_commit:.2f} s"}

    def _not_committed(self, m: int, loss: float, t0: float, exc: Exception) -> dict:
        """The memory refused the commit because the lease is gone: it ran out while QT trained (a long
        round on a loaded machine; the memory's lease_timeout_s) or the memory restarted. Its sets are back
        at the front of TM for the next reduction, so the learner goes on with the RTM it has (0 sets
        reduced) instead of stopping; QT keeps this round's training and is published."""
        self.publish_model()
        self.last_duration_s = time.monotonic() - t0
        message = (f"{m} sets trained on but not committed after {self.last_duration_s:.1f} s ({exc}); if the lease "
                   f"ran out, raise the memory's lease_timeout_s; the sets are back in TM for the next reduction")
        self.get_logger().warning(message)
        return {"sets_reduced": 0, "rtm_size": int(self.memory.stats()["rtm_size"]),
                "qt_version": int(self.qt.version), "qt_loss": loss, "duration_s": self.last_duration_s,
                "message": message}

    def _on_reduce(self, request: Reduce.Request, response: Reduce.Response):
        try:
            out = self.reduce(request.max_sets, request.epochs)
        except ServiceError as exc:
            response.success = False
            response.message = (f"{exc} (is the memory node /{self.memory_name} running? set "
                                 f"memory_node:=<name> if it has another name)")
            self.get_logger().warning(f"reduce failed: {response.message}")
            return response
        except Exception as exc:   # a bug or bad data: report and keep serving
            response.success = False
            response.message = f"internal error: {type(exc).__name__}: {exc}"
            self.get_logger().error(f"reduce failed: {response.message}")
            return response
        response.success = True
        response.message = out["message"]
        response.sets_reduced = out["sets_reduced"]
        response.rtm_size = out["rtm_size"]
        response.qt_version = out["qt_version"]
        response.qt_loss = out["qt_loss"]
        response.duration_s = out["duration_s"]
        return response

    def _on_timer(self) -> None:
        if not self.memory.ready():
            return
        try:
            out = self.reduce()
            if out["sets_reduced"]:
                self.get_logger().info(f"timer reduction: {out['sets_reduced']} sets, QT v{out['qt_version']}, "
                                       f"loss {out['qt_loss']:.4g}, {out['duration_s']:.2f} s")
        except Exception as exc:
            self.get_logger().warning(f"timer reduction failed: {exc}")


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent qt_trainer_node``: 0 on Ctrl-C, 1 when it cannot start.
    Multi-threaded: the reduce service waits on nested calls to the memory node."""
    from comper_agent.core.networks import configure_torch
    return serve_node(QtTrainerNode, "qt_trainer_node", args,
                      on_ready=lambda node: configure_torch(node.p.num_threads or 1))


if __name__ == "__main__":
    sys.exit(main())
