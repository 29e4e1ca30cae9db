"""ExperienceCheckpoint: the experience a learner samples, saved beside each checkpoint and restored on
resume (``checkpoint_replay``), so a run split over several sessions learns as one would.

* Memory-backed learners (COMPER variants, COMCACT, async DDPG): the memory node's whole state as a
  verified snapshot through its ``~/snapshot`` service, once no reduction is in flight and what the
  learner still holds for the memory has gone out (``quiesce``). Embedded bring-up: the embedded memory
  node's ``snapshot_root`` is the run's ``checkpoints/`` folder and the snapshot is ``step_<N>.memory``
  beside ``step_<N>.pt`` (pruned with it, :meth:`RunDir.save_checkpoint`), and so for an external memory node
  whose ``snapshot_root`` is that folder (``ros2 run comper_agent bringup`` starts it so); another external one:
  ``<run_id>/step_<N>.memory`` under its own ``snapshot_root``, on its machine. On resume an embedded memory
  node restores it in process (``MemoryNode.restore_snapshot``); an external one through ``~/snapshot``, which
  it allows only when started with ``snapshot_service:=save_restore``, or when it loaded that snapshot at
  start-up (``snapshot_restore``) and nothing changed since.
* Learners with a local replay buffer (DQN, lock-step DDPG): ``step_<N>.replay.npz`` (the buffer's
  ``state_arrays``: numpy arrays only, read without unpickling).

The checkpoint records what was saved (``state["replay"]``); the snapshot or file is written first, so a
checkpoint never names something that is not there.
"""
from __future__ import annotations

from comper_msgs_py.service_client import ServiceError

__all__ = ["ExperienceCheckpoint", "SNAPSHOT_TIMEOUT_S"]

#: seconds a memory snapshot or restore may take (an Atari memory of ~20,000 4-frame identities is ~1 GB;
#: restoring rebuilds its index: ~5 ms per identity here)
SNAPSHOT_TIMEOUT_S = 600.0


class ExperienceCheckpoint:
    """node: the learner's harness (its ``mem``, ``run_dir``, ``run_id``, ``embedded``, ``outputs``, ``p``,
    ``log``, and ``node``, the rclpy node). ``replay``: the learner's local replay buffer, set by a learner that
    has one. ``quiesce``: called before a memory snapshot (default: the re-stored batches waiting are stored);
    a learner that holds steps not yet stored sets its own."""

    def __init__(self, node):
        self.node = node
        self.replay = None
        self.quiesce = lambda: node.mem.store(None)
        self.warned = False
        self.error = ""          # why the last save gave no memory snapshot ("" when it did)
        self._beside: bool | None = None

    def beside_checkpoints(self) -> bool:
        """Whether the memory node's snapshot_root is this run's checkpoints folder (asked once): the embedded
        memory node's, or an external one's set so (``ros2 run comper_agent bringup`` does). Its snapshots are
        then named ``step_<N>.memory`` beside ``step_<N>.pt`` and pruned with it; otherwise ``<run_id>/...``,
        kept apart from the other runs a memory node may serve."""
        if self._beside is None:
            node = self.node
            if node.embedded is not None and node.embedded.memory is not None:
                self._beside = True
            else:
                import os
                root = self._memory_parameter("snapshot_root")
                self._beside = bool(root) and os.path.realpath(root) == os.path.realpath(node.run_dir.checkpoints)
        return self._beside

    def _memory_parameter(self, name: str) -> str:
        """A string parameter of the external memory node, read through its parameter service ('' when unset
        or unreadable)."""
        from rcl_interfaces.srv import GetParameters
        from comper_msgs_py.service_client import call
        node = self.node.node
        p = self.node.p
        client = node.create_client(GetParameters, f"/{p.memory_node.strip('/')}/get_parameters")
        try:
            if not client.wait_for_service(timeout_sec=p.service_timeout_s):
                return ""
            values = call(client, GetParameters.Request(names=[name]), p.service_timeout_s).values
        except ServiceError:
            return ""
        finally:
            node.destroy_client(client)
        return values[0].string_value if values else ""

    @property
    def kept(self) -> bool:
        """Whether this run's checkpoints save experience: checkpoint_replay, and a memory or a replay buffer."""
        node = self.node
        has_experience = node.mem is not None or self.replay is not None
        return bool(node.p.checkpoint_replay) and has_experience

    @property
    def timeout(self) -> float:
        return max(self.node.p.service_timeout_s, SNAPSHOT_TIMEOUT_S)

    def save(self, step: int) -> dict | None:
        """Save the experience beside the checkpoint of `step`; what the checkpoint records about it, or None
        when there is nothing to save or the memory node refused (warned once: the checkpoints then hold
        weights and counters only)."""
        node = self.node
        if node.mem is not None:
            name = node.run_dir.replay_path(step, "memory").name
            request = name if self.beside_checkpoints() else f"{node.run_id}/{name}"
            try:
                if node.mem.in_flight is not None:
                    node.mem.collect(wait=True)
                self.quiesce()
                path, _ = node.mem.memory.snapshot(request, timeout=self.timeout)
                self.error = ""
            except ServiceError as exc:     # refused, or the memory node is gone: the checkpoint goes on without
                self.error = f"no snapshot from the memory node: {exc}"
                if not self.warned:
                    self.warned = True
                    node.log.warning(f"checkpoints hold no memory contents: no snapshot from the memory node ({exc}); "
                                     "an external memory node needs -p snapshot_root:=DIR (or set "
                                     "checkpoint_replay:=false)")
                return None
            return {"kind": "memory", "request": request, "path": path}
        replay = self.replay
        if replay is None:
            return None
        from comper_agent.core.checkpoint import save_arrays
        f = save_arrays(node.run_dir.replay_path(step, "local"), replay.state_arrays())
        return {"kind": "local", "file": f.name, "transitions": len(replay)}

    @staticmethod
    def describe(saved: dict) -> str:
        """What a checkpoint's ``replay`` record holds, for the log."""
        if saved["kind"] == "memory":
            return f"the memory's snapshot {saved['path']}"
        return f"the replay buffer, {saved['transitions']} transitions, {saved['file']}"

    def restore(self, saved: dict | None) -> None:
        """On resume, before anything is stored: the saved experience back into the memory node or the
        replay buffer. RuntimeError (the caller ends the start) when it is missing or does not fit. A
        checkpoint without it (older, or saved with checkpoint_replay off) resumes with an empty one."""
        node = self.node
        replay = self.replay
        if saved is None:
            if node.mem is not None or replay is not None:
                node.log.warning("the checkpoint holds no memory / replay contents: they refill from this step")
            return
        if not node.p.checkpoint_replay:
            node.log.warning("checkpoint_replay:=false: the memory / replay contents saved with the checkpoint are "
                             "not restored; they refill from this step")
            return
        if saved["kind"] == "memory" and node.mem is not None:
            from comper_memory.core import SnapshotError
            embedded = node.embedded.memory if node.embedded is not None else None
            try:    # an embedded memory node restores in process: its ~/snapshot refuses peers' restores
                path, _ = (embedded.restore_snapshot(saved["request"]) if embedded is not None
                           else node.mem.memory.restore(saved["request"], timeout=self.timeout))
            except (ServiceError, SnapshotError) as exc:
                raise RuntimeError(f"cannot restore the memory saved with the checkpoint ({saved['path']}): {exc}; "
                                   "resume with -p checkpoint_replay:=false to continue with an empty memory") from None
            st = node.mem.stats()
            node.log.info(f"memory restored from {path}: {st['identities']} identities, TM sets {st['tm_sets']}, "
                          f"RTM {st['rtm_size']}")
        elif saved["kind"] == "local" and replay is not None:
            from comper_agent.core.checkpoint import load_arrays
            f = node.outputs.resume_path.parent / saved["file"]
            try:
                replay.load_state_arrays(load_arrays(f))
            except (OSError, ValueError) as exc:
                raise RuntimeError(f"cannot restore the replay buffer saved with the checkpoint ({f}): {exc}; "
                                   "resume with -p checkpoint_replay:=false to continue with an empty one") from None
            node.log.info(f"replay buffer restored from {f}: {len(replay)} transitions")
        else:
            raise RuntimeError(f"the checkpoint's {saved['kind']} replay contents do not fit this run's learner")
