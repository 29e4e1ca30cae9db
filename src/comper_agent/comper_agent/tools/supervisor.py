"""``ros2 run comper_agent bringup``: the suite as separate processes from one command, supervised.

    ros2 run comper_agent bringup                                   # comcact_node + sim, memory, QT trainer
    ros2 run comper_agent bringup --learner comcact_node --ros-args -p env_id:=Hopper-v4 -p total_steps:=50000
    ros2 run comper_agent bringup --learner comper_node --ros-args -p env_id:=CartPole-v1
    ros2 run comper_agent bringup --dry-run --ros-args -p algorithm:=ddpg    # print the plan only

What the learner's ``bringup:=external`` needs, each node in its own process: ``sim_node``, and for the
variants that use them ``memory_node`` and ``qt_trainer_node`` (the same choice as the learner's embedded
bring-up: COMCACT and COMPER / COMPER-M use all three, COMPER-F and ``reducer:=memory`` no QT trainer,
DDPG and DQN the simulation only), then the learner with ``-p bringup:=external``. The nodes are named by
the learner's ``sim_node`` / ``memory_node`` / ``qt_trainer_node`` parameters.

Parameters: each ``-p`` (and each ``--params-file`` value) goes to the processes whose node declares it, as
the embedded bring-up gives the command line to every node and each takes what it declares (``-p env_id:=...``
reaches the sim and the learner, ``-p delta:=...`` the memory); a name no node declares is refused before
anything starts; ``-r __node:=...`` renames the learner only; other arguments go to every process
(:mod:`comper_agent.tools.bringup_plan`). The supervisor adds the wiring: each node's name, the run id (sim and learner) and the
memory node's ``snapshot_root`` (the run's checkpoints folder: checkpoints hold the memory, and a resume
continues with it, as in the embedded bring-up), the sim's ``env_id`` (the learner's, default included: the
sim node's own default is another task), the QT trainer's ``memory_node`` (and ``architecture:=comper`` for
comper_node). ALE settings that the learner's profile fixes (``frame_stack``, ``frame_pooling``) are not
derived: give them on the command line, where they reach the sim and the learner alike (the learner names a
mismatch at start). ``mode:=async`` is refused: its actor processes are started by the learner in the
embedded bring-up only.

Supervision: the servers start first; the learner starts when their services are in the ROS graph
(``--ready-timeout``). Every output line is printed prefixed with ``[<node name>]``. SIGINT / SIGTERM
are forwarded once, to the learner first (it finishes its step and saves a checkpoint, which may need the
servers), then to the servers; a second signal is forwarded to all at once (the learner then aborts).
When the learner finishes, the servers are stopped and the exit status is the learner's. When a node
exits on its own otherwise (a server at any time, the learner with a non-zero status), the supervisor
prints ``[bringup] <name> exited with code N``, stops the others the same way and exits non-zero (the
node's code, 128 + signal for a node killed by a signal, 1 for a server that exited with 0). A process
that does not stop within ``--stop-timeout`` seconds of SIGINT gets SIGTERM, then SIGKILL. If the supervisor
itself dies (even by SIGKILL), every child gets SIGTERM from the kernel (PR_SET_PDEATHSIG) and stops.

The pure part (which processes, with which arguments: :func:`plan`, :mod:`comper_agent.tools.bringup_plan`) is unit-tested; the
supervision by test/integration/test_bringup_supervisor.py.
"""
from __future__ import annotations

import argparse
import functools
import os
import signal
import subprocess
import sys
import threading
import time

from comper_agent.tools.bringup_plan import LEARNERS, ProcSpec, plan

__all__ = ["Supervisor", "plan", "main"]       # plan: also what the launch file imports from here


# ----------------------------------------------------------------------------------------- supervision
def _executable_path(spec: ProcSpec) -> str:
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    try:
        path = os.path.join(get_package_prefix(spec.package), "lib", spec.package, spec.executable)
    except PackageNotFoundError:
        raise ValueError(f"package {spec.package} not found: is the workspace built and sourced (env.sh)?") from None
    if not os.access(path, os.X_OK):
        raise ValueError(f"no executable {spec.executable} in package {spec.package}")
    return path


def _exit_text(rc: int) -> str:
    if rc < 0:
        try:
            return f"was killed by {signal.Signals(-rc).name}"
        except ValueError:
            return f"was killed by signal {-rc}"
    return f"exited with code {rc}"


class Supervisor:
    def __init__(self, procs: list[ProcSpec], *, stop_timeout: float, ready_timeout: float, out=None):
        self.specs = procs
        self.stop_timeout = stop_timeout
        self.ready_timeout = ready_timeout
        self.out = out or sys.stdout
        self.children: dict[str, subprocess.Popen] = {}
        self.readers: list[threading.Thread] = []
        self.signals = 0
        self.lock = threading.Lock()
        self.wake = threading.Event()

    def say(self, text: str) -> None:
        self.emit("bringup", text)

    def emit(self, name: str, line: str) -> None:
        with self.lock:
            self.out.write(f"[{name}] {line}\n")
            self.out.flush()

    def _pump(self, name: str, stream) -> None:
        for raw in iter(stream.readline, b""):
            self.emit(name, raw.decode(errors="replace").rstrip("\n"))
        stream.close()
        self.wake.set()

    def start(self, spec: ProcSpec) -> None:
        from comper_agent.recording.recording_link import _die_with_parent
        cmd = spec.command(_executable_path(spec))
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        # a session of its own: a terminal's Ctrl-C reaches the supervisor only, which forwards it once;
        # PR_SET_PDEATHSIG: a child gets SIGTERM (and stops cleanly) if the supervisor dies, even by SIGKILL
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, env=env,
                                preexec_fn=functools.partial(_die_with_parent, os.getpid()))
        self.children[spec.name] = proc
        t = threading.Thread(target=self._pump, args=(spec.name, proc.stdout), daemon=True, name=f"log-{spec.name}")
        t.start()
        self.readers.append(t)
        self.say(f"started {spec.name} (pid {proc.pid}): ros2 run {spec.package} {spec.executable} "
                 + " ".join(["--ros-args", *spec.ros_args] if spec.ros_args else []))

    def on_signal(self, signum, _frame) -> None:
        # no self.wake.set() here: the handler runs in the main thread, possibly inside wake.wait / wake.set with
        # the event's lock held, and would then wait for that lock for ever; the loops look at self.signals
        # every 0.1-0.2 s
        self.signals += 1

    def _send(self, names, sig) -> None:
        for n in names:
            p = self.children.get(n)
            if p is not None and p.poll() is None:
                try:
                    os.killpg(p.pid, sig)
                except ProcessLookupError:
                    pass

    def _exited(self) -> list[str]:
        return [n for n, p in self.children.items() if p.poll() is not None]

    def _wait_ready(self) -> bool:
        """True when every started server's services are in the graph; False on a signal or a death."""
        services = [s for spec in self.specs if not spec.learner and spec.name in self.children for s in spec.services]
        if not services:
            return True
        import rclpy
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions
        ctx = rclpy.Context()
        rclpy.init(args=[], context=ctx, signal_handler_options=SignalHandlerOptions.NO)   # ours stay
        node = Node(f"_bringup_{os.getpid()}", context=ctx, start_parameter_services=False)
        start = time.monotonic()
        try:
            while True:
                present = {n for n, _ in node.get_service_names_and_types()}
                if all(s in present for s in services):
                    self.say(f"servers ready after {time.monotonic() - start:.1f} s")
                    return True
                if self.signals or self._exited():
                    return False
                if time.monotonic() - start > self.ready_timeout:
                    missing = [s for s in services if s not in present]
                    self.say(f"services not in the graph after {self.ready_timeout:g} s: {', '.join(missing)}")
                    return False
                self.wake.wait(0.2)
                self.wake.clear()
        finally:
            node.destroy_node()
            ctx.try_shutdown()

    def stop_all(self) -> None:
        """Learner first (it saves, maybe through the servers), then the servers; SIGINT, then SIGTERM, then
        SIGKILL, each after stop_timeout. A further signal to the supervisor sends SIGINT to all at once."""
        signals_seen = self.signals
        groups = [[s.name for s in self.specs if s.learner], [s.name for s in self.specs if not s.learner]]
        for group in groups:
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
                alive = [n for n in group if n in self.children and self.children[n].poll() is None]
                if not alive:
                    break
                if sig != signal.SIGINT:
                    self.say(f"{', '.join(alive)} still running after {self.stop_timeout:g} s: sending {sig.name}")
                self._send(alive, sig)
                deadline = time.monotonic() + self.stop_timeout
                while any(self.children[n].poll() is None for n in alive) and time.monotonic() < deadline:
                    if self.signals > signals_seen:        # impatient user: everyone, now
                        signals_seen = self.signals
                        self._send(list(self.children), signal.SIGINT)
                    self.wake.wait(0.1)
                    self.wake.clear()

    def run(self) -> int:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self.on_signal)
        learner = next(s for s in self.specs if s.learner)
        rc = 0
        try:
            came_up = True
            for spec in self.specs:
                if spec.learner and not self._wait_ready():
                    came_up = False
                    break
                if self.signals or self._exited():
                    break
                self.start(spec)
            failed: str | None = None
            while not self.signals:
                done = self._exited()
                if done:
                    failed = done[0]
                    break
                if not came_up:
                    break
                self.wake.wait(0.2)
                self.wake.clear()
            if self.signals:
                self.say(f"signal received: stopping {', '.join(self.children)}")
            elif failed is not None:
                code = self.children[failed].returncode
                if failed == learner.name and code == 0:
                    self.say(f"{failed} finished; stopping the servers")
                else:
                    self.say(f"{failed} {_exit_text(code)}; stopping the others")
                    rc = code if code > 0 else (128 - code if code < 0 else 1)
            else:
                self.say("the servers did not come up; stopping them")
                rc = 1
            self.stop_all()
            lc = self.children.get(learner.name)
            if rc == 0 and lc is not None and lc.returncode not in (0, None):
                rc = lc.returncode if lc.returncode > 0 else 128 - lc.returncode
        finally:
            for p in self.children.values():     # never leave a process behind
                if p.poll() is None:
                    try:
                        os.killpg(p.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    p.wait()
            for t in self.readers:
                t.join(5)
        self.say("exit codes: " + ", ".join(f"{n} {p.returncode}" for n, p in self.children.items())
                 + f"; bring-up exits with {rc}")
        return rc


def main(args=None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    ros_args: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], [a for a in argv[i + 1:] if a != "--"]
    parser = argparse.ArgumentParser(
        prog="ros2 run comper_agent bringup",
        description="Start the suite as separate processes (sim, memory, QT trainer, the learner with "
                    "bringup:=external) and supervise them: prefixed logs, signals forwarded, a node that dies "
                    "stops the rest (non-zero exit). The --ros-args go to every process.",
        epilog="Example: ros2 run comper_agent bringup --learner comcact_node --ros-args -p env_id:=Hopper-v4")
    parser.add_argument("--learner", default="comcact_node", choices=LEARNERS, help="the learner node (default "
                        "comcact_node)")
    parser.add_argument("--stop-timeout", type=float, default=30.0,
                        help="seconds a process gets after SIGINT (then SIGTERM, then SIGKILL); default 30")
    parser.add_argument("--ready-timeout", type=float, default=180.0,
                        help="seconds to wait for the servers' services before giving up; default 180")
    parser.add_argument("--dry-run", action="store_true", help="print the processes and their arguments, start nothing")
    opts = parser.parse_args(argv)
    try:
        procs = plan(opts.learner, ros_args)
    except (ValueError, OSError) as exc:
        print(f"bringup: {exc}", file=sys.stderr)
        return 2
    if opts.dry_run:
        for p in procs:
            print(f"{p.name}: ros2 run {p.package} {p.executable} " + " ".join(["--ros-args", *p.ros_args]))
        return 0
    try:
        for p in procs:
            _executable_path(p)
    except ValueError as exc:
        print(f"bringup: {exc}", file=sys.stderr)
        return 2
    return Supervisor(procs, stop_timeout=opts.stop_timeout, ready_timeout=opts.ready_timeout).run()


if __name__ == "__main__":
    sys.exit(main())
