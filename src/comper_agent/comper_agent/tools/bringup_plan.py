"""Which processes ``ros2 run comper_agent bringup`` (and the launch file) starts, with which arguments: the pure
part of the bring-up, unit-tested in test/unit/test_bringup_plan.py; the supervision is :mod:`comper_agent.tools.supervisor`.

* :func:`plan` - the processes for a learner and the user's ``--ros-args``: ``sim_node``, ``memory_node`` and
  ``qt_trainer_node`` as the variant uses them, the learner last with ``bringup:=external``, wired by name.
* Parameters: every node refuses a ``-p`` it does not declare, so the command line is split (:class:`RosArgs`):
  each ``-p`` and each params-file value goes to the processes whose node declares it (:func:`node_parameters`,
  from the nodes' config classes), a ``-p <node>:name:=v`` or a file's ``<node>:`` section to that node only;
  a name that none of the bring-up's nodes declares is refused before anything starts, with the nearest names,
  as the embedded bring-up refuses one that none of its nodes declares.
* The run (:func:`run_plan`): decided before anything starts, so the memory node can write into it: the run id
  (``-p run_id`` or ``<algorithm>-<env>-s<seed>-<time>``) goes to the sim and the learner, and the memory node's
  ``snapshot_root`` is the run's ``checkpoints/`` folder: each checkpoint's memory snapshot lies beside it and is
  pruned with it, as in the embedded bring-up. On ``-p resume`` the run is the checkpoint's, and the memory node
  loads the snapshot the checkpoint names at start-up (``snapshot_restore``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

__all__ = ["ProcSpec", "RunPlan", "RosArgs", "plan", "run_plan", "parse_ros_args", "node_parameters",
           "learner_config", "LEARNERS", "RCLPY_PARAMETERS"]

LEARNERS = ("comcact_node", "comper_node")
DEFAULT_ALGORITHM = {"comcact_node": "comcact", "comper_node": "comper"}


@dataclass
class ProcSpec:
    """One process of the bring-up: ``ros2 run <package> <executable> --ros-args <ros_args>``."""
    name: str
    package: str
    executable: str
    ros_args: list[str] = field(default_factory=list)
    services: list[str] = field(default_factory=list)     # what must be in the graph before the learner starts
    learner: bool = False

    def command(self, executable_path: str | None = None) -> list[str]:
        exe = executable_path or self.executable
        return [exe, "--ros-args", *self.ros_args] if self.ros_args else [exe]


def _is_node_remap(flag: str, value: str | None) -> bool:
    """``-r __node:=name`` (or ``--remap``, ``__name``, ``<node>:__node``): a rename of the node."""
    return (flag in ("-r", "--remap") and value is not None and ":=" in value
            and value.split(":=", 1)[0].split(":")[-1] in ("__node", "__name"))


@dataclass
class RosArgs:
    """The user's ``--ros-args`` taken apart, so that each process gets the parameters its node declares."""
    settings: list[tuple]     # in command-line order (rcl: a later setting wins): ("-p", text, node named or '',
                              # parameter) for each -p as given, ("file", path, its YAML) for each --params-file
    other: list[str]          # everything else (remaps but the learner's rename, --log-level, ...)
    name: str                 # the learner's node name

    def _reaching(self, node: str, files: bool = True):
        """(name, value, the -p text or None) of each setting that reaches the node named `node`, in order: a
        file's ``/**``, ``node`` and ``/node`` sections; a ``-p``, or a ``-p node:name:=v`` naming this node."""
        import yaml
        for item in self.settings:
            if item[0] == "-p":
                _, text, target, name = item
                if target in ("", node):
                    value = text.split(":=", 1)[1]
                    yield name, (yaml.safe_load(value) if value else ""), text
            elif files:
                _, path, doc = item
                for section in ("/**", node, "/" + node):
                    entry = doc.get(section) or {}
                    params = entry.get("ros__parameters") if isinstance(entry, dict) else None
                    if params is not None and not isinstance(params, dict):
                        raise ValueError(f"--params-file {path}: section {section!r} has no ros__parameters mapping")
                    for name, value in (params or {}).items():
                        yield name, value, None

    def values(self, node: str, *, files: bool = True) -> dict:
        """The parameter values that reach the node named `node` (`files` False: from ``-p`` only)."""
        return {name: value for name, value, _ in self._reaching(node, files)}

    def route(self, node: str, declared: frozenset, wired: tuple = ()) -> list[str]:
        """The arguments for the process of `node`, which declares `declared`: the other arguments, then, in their
        order, the ``-p`` it declares as given and each params-file value it declares as a ``-p`` (a file names
        other nodes' parameters too, which a node refuses); not those in `wired` (the bring-up sets them)."""
        out = list(self.other)
        for name, value, text in self._reaching(node):
            if name in declared and name not in wired:
                out += ["-p", text or f"{name}:={_yaml_value(value)}"]
        return out


def _yaml_value(value) -> str:
    """A parameter value as the YAML text of a ``-p name:=<text>`` (rcl reads it back as the same type)."""
    import yaml
    text = yaml.safe_dump(value, default_flow_style=True, width=2**31).rstrip("\n")
    return text[:-4] if text.endswith("\n...") else text


def parse_ros_args(ros_args: list[str], learner_name: str) -> RosArgs:
    """The ``-p``/``--param`` settings, the ``--params-file`` files (loaded), the other arguments (without the
    learner's ``-r __node:=`` remap) and the learner's name."""
    import yaml
    settings, other = [], []
    name = learner_name
    i = 0
    while i < len(ros_args):
        a = ros_args[i]
        nxt = ros_args[i + 1] if i + 1 < len(ros_args) else None
        if a in ("-p", "--param") and nxt is not None and ":=" in nxt:
            key = nxt.split(":=", 1)[0].split(":")
            settings.append(("-p", nxt, key[0].strip("/") if len(key) > 1 else "", key[-1]))
            i += 2
        elif a == "--params-file" and nxt is not None:
            try:
                with open(nxt) as f:
                    doc = yaml.safe_load(f) or {}
            except (OSError, yaml.YAMLError) as exc:
                raise ValueError(f"--params-file {nxt}: {exc}") from None
            if not isinstance(doc, dict):
                raise ValueError(f"--params-file {nxt}: not a mapping of node names to ros__parameters")
            settings.append(("file", nxt, doc))
            i += 2
        elif _is_node_remap(a, nxt):
            name = nxt.split(":=", 1)[1]
            i += 2
        else:
            other.append(a)
            i += 1
    return RosArgs(settings, other, name)


#: the parameters rclpy declares on every node
RCLPY_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})


def node_parameters(executable: str, *, algorithm: str = "", architecture: str = "comcact") -> frozenset:
    """The parameters the node of `executable` declares: its config classes' fields (what its constructor declares
    with declare_config) and rclpy's own. `algorithm`: the learner's; `architecture`: the QT trainer's."""
    import dataclasses
    if executable == "sim_node":
        from comper_sim.core.config import SimConfig
        classes = [SimConfig]
    elif executable == "memory_node":
        from comper_memory.core import MemoryConfig
        from comper_memory.memory_node import MemoryNodeConfig
        classes = [MemoryConfig, MemoryNodeConfig]
    elif executable == "qt_trainer_node":
        from comper_agent.core.config import QT_CONFIGS
        from comper_agent.nodes.node_config import QtTrainerNodeConfig
        classes = [QtTrainerNodeConfig, QT_CONFIGS[architecture]]
    else:
        from comper_agent.nodes import node_config
        classes = [node_config.ComcactNodeConfig if executable == "comcact_node" else node_config.ComperNodeConfig,
                   learner_config(algorithm)]
    return RCLPY_PARAMETERS | {f.name for c in classes for f in dataclasses.fields(c)}


def learner_config(algorithm: str):
    """The learner's hyper-parameter class of `algorithm` (the learner nodes' LEARNER_CONFIGS, without importing
    them: they import torch)."""
    from comper_agent.core import config
    return {"comcact": config.ComcactConfig, "ddpg": config.DDPGConfig, "comper": config.ComperConfig,
            "comper_f": config.ComperConfig, "comper_m": config.ComperConfig, "dqn": config.DQNConfig}[algorithm]


def _refuse_unknown(args: RosArgs, procs: list[ProcSpec], declared: dict) -> None:
    """ValueError naming every parameter given that reaches none of the bring-up's nodes that declares it (as each
    node refuses a parameter that no node of its process declares)."""
    import difflib
    reaching = {p.name: set(args.values(p.name)) for p in procs}
    known = set().union(*(reaching[p.name] & declared[p.name] for p in procs))
    unknown = sorted(set().union(*reaching.values()) - known)
    if not unknown:
        return
    every = sorted(set().union(*declared.values()))
    nodes = ", ".join(p.name for p in procs)
    lines = []
    for name in unknown:
        near = difflib.get_close_matches(name, every, n=3, cutoff=0.6)
        lines.append(f"`{name}` is not a parameter of the bring-up's nodes ({nodes})"
                     + ("; did you mean " + " or ".join(f"`{c}`" for c in near) + "?" if near else ""))
    raise ValueError("; ".join(lines))


def plan(learner: str, ros_args: list[str], *, now: float | None = None) -> list[ProcSpec]:
    """The processes for ``learner`` with the user's ``ros_args``: servers first, the learner last, each with the
    parameters its node declares; `now`: the time a default run id is named after (None = now). ValueError for
    what the bring-up cannot run, and for a parameter that none of its nodes declares."""
    if learner not in LEARNERS:
        raise ValueError(f"--learner must be one of {', '.join(LEARNERS)}, not {learner!r}")
    args = parse_ros_args(ros_args, learner)
    learner_name = args.name
    values = args.values(learner_name)
    algorithm = str(values.get("algorithm", DEFAULT_ALGORITHM[learner]))
    if str(values.get("mode", "sync")) == "async":
        raise ValueError("mode:=async is not supported by the bring-up (the learner starts its actor processes "
                         "in the embedded bring-up only): run the learner alone, e.g. ros2 run comper_agent "
                         "comcact_node --ros-args -p mode:=async")
    # a parameter file written for the learner alone may say bringup: embedded; a -p saying so contradicts
    if str(args.values(learner_name, files=False).get("bringup", "external")) != "external":
        raise ValueError("bringup:=embedded contradicts a multi-process bring-up: leave bringup unset")
    if learner == "comcact_node":
        if algorithm not in ("comcact", "ddpg"):
            raise ValueError(f"comcact_node has no algorithm {algorithm!r} (comcact, ddpg)")
        uses_memory = uses_qt = algorithm == "comcact"
    else:
        if algorithm not in ("comper", "comper_f", "comper_m", "dqn"):
            raise ValueError(f"comper_node has no algorithm {algorithm!r} (comper, comper_f, comper_m, dqn)")
        uses_memory = algorithm != "dqn"
        reducer = str(values.get("reducer", "auto"))
        uses_qt = uses_memory and (reducer == "qt_trainer" or (reducer == "auto" and algorithm != "comper_f"))
    names = {k: str(values.get(k, k)).strip("/") for k in ("sim_node", "memory_node", "qt_trainer_node")}
    # the task is the learner's (its default differs from the sim node's), as the embedded bring-up gives it
    env_id = str(values.get("env_id", _learner_default(learner, "env_id")))
    run = run_plan(learner, algorithm, env_id, values, now=now)
    sim = names["sim_node"]
    declared = {sim: node_parameters("sim_node"), learner_name: node_parameters(learner, algorithm=algorithm)}
    procs = [ProcSpec(sim, "comper_sim", "sim_node",
                      [*args.route(sim, declared[sim], ("env_id", "run_id")), "-p", f"env_id:={env_id}",
                       "-p", f"run_id:={run.run_id}", "-r", f"__node:={sim}"],
                      services=[f"/{sim}/step"])]
    if uses_memory:
        mem = names["memory_node"]
        declared[mem] = node_parameters("memory_node")
        # checkpoints hold the memory as in the embedded bring-up: its snapshot_root is the run's checkpoints/
        # folder (step_<N>.memory beside step_<N>.pt, pruned with it); a resume loads the checkpoint's at start
        snapshots = {}
        if bool(values.get("checkpoint_replay", True)) and "snapshot_root" not in args.values(mem):
            snapshots["snapshot_root"] = run.snapshot_root
            if run.restore and "snapshot_restore" in declared[mem]:
                snapshots["snapshot_restore"] = run.restore
        procs.append(ProcSpec(mem, "comper_memory", "memory_node",
                              [*args.route(mem, declared[mem], tuple(snapshots)),
                               *(x for k, v in snapshots.items() for x in ("-p", f"{k}:={v}")),
                               "-r", f"__node:={mem}"],
                              services=[f"/{mem}/store"]))
    if uses_qt:
        qt = names["qt_trainer_node"]
        # comper_node's QT is COMPER's; comcact_node's the trainer's default unless given
        wiring = {"memory_node": names["memory_node"],
                  **({"architecture": "comper"} if learner == "comper_node" else {})}
        architecture = str(wiring.get("architecture", args.values(qt).get("architecture", "comcact")))
        try:
            declared[qt] = node_parameters("qt_trainer_node", architecture=architecture)
        except KeyError:
            raise ValueError(f"qt_trainer_node has no architecture {architecture!r}") from None
        procs.append(ProcSpec(qt, "comper_agent", "qt_trainer_node",
                              [*args.route(qt, declared[qt], tuple(wiring)),
                               *(x for k, v in wiring.items() for x in ("-p", f"{k}:={v}")), "-r", f"__node:={qt}"],
                              services=[f"/{qt}/reduce"]))
    rename = ["-r", f"__node:={learner_name}"] if learner_name != learner else []
    run_id = [] if run.resumed or "run_id" in values else ["-p", f"run_id:={run.run_id}"]
    procs.append(ProcSpec(learner_name, "comper_agent", learner,
                          [*args.route(learner_name, declared[learner_name], ("bringup",)), "-p", "bringup:=external",
                           *run_id, *rename], learner=True))
    _refuse_unknown(args, procs, declared)
    return procs


@dataclass
class RunPlan:
    """The learner's run directory, decided before anything starts (the memory node writes into it)."""
    run_id: str
    path: str                   # absolute
    resumed: bool = False
    snapshot_root: str = ""     # the run's checkpoints/ folder, absolute
    restore: str = ""           # resume: the memory snapshot the checkpoint names ('' = none)


def run_plan(learner: str, algorithm: str, env_id: str, values: dict, *, now: float | None = None) -> RunPlan:
    """The run the learner will write: ``-p run_id`` (default ``<algorithm>-<env>-s<seed>-<time>`` at `now`) under
    ``-p runs_root``, or on ``-p resume`` the checkpoint's run (as the learner resolves it: run_io.resume_checkpoint)
    and the memory snapshot it names. ValueError when the checkpoint cannot be read."""
    from comper_agent.nodes.run_io import default_run_id
    resume = str(values.get("resume", "") or "")
    if not resume:
        seed = int(values.get("seed", _learner_default(learner, "seed", learning=True)))
        run_id = str(values.get("run_id", "") or "") or default_run_id(algorithm, env_id, seed, now=now)
        path = os.path.abspath(os.path.join(str(values.get("runs_root", _learner_default(learner, "runs_root"))),
                                            run_id))
        return RunPlan(run_id, path, snapshot_root=os.path.join(path, "checkpoints"))
    from comper_agent.nodes.run_io import resume_checkpoint
    try:
        ck, state, _ = resume_checkpoint(resume)
        run_id = str(state["run"]["run_id"])
    except KeyError as exc:
        raise ValueError(f"resume:={resume}: the checkpoint has no {exc}: not a learner's checkpoint") from None
    except (OSError, RuntimeError, ValueError) as exc:
        raise ValueError(f"resume:={resume}: {exc}") from None
    path = os.path.abspath(os.path.join(ck.parent.parent.parent, run_id))
    root = os.path.join(path, "checkpoints")
    saved = state.get("replay") or {}
    restore = ""
    if saved.get("kind") == "memory" and os.path.isdir(os.path.join(root, saved.get("request", ""))):
        restore = saved["request"]
    return RunPlan(run_id, path, resumed=True, snapshot_root=root, restore=restore)


def _learner_default(learner: str, name: str, *, learning: bool = False):
    """The default of a node parameter of the learner (`learning`: of a learning parameter, e.g. seed)."""
    import dataclasses
    if learning:
        from comper_agent.core.config import ComcactConfig, ComperConfig
        cls = ComcactConfig if learner == "comcact_node" else ComperConfig
    else:
        from comper_agent.nodes.node_config import ComcactNodeConfig, ComperNodeConfig
        cls = ComcactNodeConfig if learner == "comcact_node" else ComperNodeConfig
    (f,) = [f for f in dataclasses.fields(cls) if f.name == name]
    return f.default
