"""Inspection verbs of the workspace's ``ros2`` stand-in (scripts/ros2-standin/ros2), for machines where
ros2cli is missing (it is not on PyPI): ``ros2 topic list|echo|hz``, ``ros2 service list``,
``ros2 node list``, ``ros2 param list|get|dump``, ``ros2 interface show`` and ``ros2 bag info``.

They take the flags users type most often with ros2cli and print what ros2cli prints for them;
each verb's ``--help`` says it is the stand-in and which flags exist. The graph comes from rclpy's
graph API (a hidden node ``_ros2cli_standin_<pid>``; there is no daemon, so each call waits
``--spin-time`` for discovery, as ``ros2 ... --no-daemon`` does), parameters from the node's
parameter services, interface texts from the ``.msg``/``.srv`` files in the ament index (nested types
parsed with rosidl_adapter), messages printed through the Python classes' rosidl introspection
(``get_fields_and_field_types``), bags read with rosbags.

The pure pieces (message to YAML, parameter nesting, rate statistics, QoS choice, interface text)
take no ROS graph and are unit-tested; the verbs are tested against running nodes.

Size: eight verbs share one graph helper, one argument convention and the message printer; one module
keeps the stand-in a single place to read and to delete where ros2cli is installed.
"""
from __future__ import annotations

import argparse
import array
import importlib
import math
import os
import signal
import sys
import time
from pathlib import Path

__all__ = ["main", "VERBS", "msg_to_plain", "msg_to_yaml", "nest_parameters", "rate_stats", "format_rate",
           "interface_text", "is_hidden_name", "choose_qos_policies", "format_param_value", "bag_info_text"]

NOTE = "[stand-in] the comper workspace's minimal replacement for ros2cli (not available from PyPI)"
VERBS = ("topic", "service", "node", "param", "interface", "bag")
DEFAULT_TRUNCATE = 128
#: the quiet spell (s) after which a list verb takes the graph as complete: Fast DDS announces a participant
#: again every 3 s, so one whose first announcements were lost or late still shows up within it
LIST_STABLE_S = 3.0


# ----------------------------------------------------------------------------------------- pure pieces
def is_hidden_name(name: str) -> bool:
    """ros2cli's rule: a topic, service or node is hidden when any part of its name starts with '_'."""
    return any(part.startswith("_") for part in name.split("/") if part)


def msg_to_plain(msg, *, truncate_length: int | None = DEFAULT_TRUNCATE, no_arr: bool = False,
                 no_str: bool = False):
    """A message (any rosidl-generated Python class) as nested dicts / lists / scalars, in field order.
    Arrays and strings longer than ``truncate_length`` end in '...' (None = full length), as ros2cli."""
    fields = getattr(type(msg), "get_fields_and_field_types", None)
    if fields is None:
        return _plain_value(msg, truncate_length, no_arr, no_str)
    out = {}
    for name, type_str in fields().items():
        value = getattr(msg, name)
        if no_arr and (type_str.startswith("sequence<") or "[" in type_str):
            out[name] = f"<array type: {type_str}>"
        elif no_str and "string" in type_str and not type_str.startswith("sequence<"):
            out[name] = f"<string length: <{len(value)}>>"
        else:
            out[name] = _plain_value(value, truncate_length, no_arr, no_str)
    return out


def _plain_value(value, truncate_length, no_arr, no_str):
    if hasattr(type(value), "get_fields_and_field_types"):
        return msg_to_plain(value, truncate_length=truncate_length, no_arr=no_arr, no_str=no_str)
    if isinstance(value, (bytes, bytearray)):
        value = list(value)
    if isinstance(value, (list, tuple, array.array)) or type(value).__name__ == "ndarray":
        items = list(value)
        cut = truncate_length is not None and len(items) > truncate_length
        items = [_plain_value(v, truncate_length, no_arr, no_str) for v in items[:truncate_length if cut else None]]
        return items + ["..."] if cut else items
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):   # numpy scalar
        value = value.item()
    if isinstance(value, str) and truncate_length is not None and len(value) > truncate_length:
        return value[:truncate_length] + "..."
    return value


def msg_to_yaml(msg, *, truncate_length: int | None = DEFAULT_TRUNCATE, no_arr: bool = False,
                no_str: bool = False, flow_style: bool = False) -> str:
    """What ``ros2 topic echo`` prints for one message (without the '---' separator)."""
    import yaml
    plain = msg_to_plain(msg, truncate_length=truncate_length, no_arr=no_arr, no_str=no_str)
    if not isinstance(plain, dict):
        return f"{plain}\n"
    return yaml.dump(plain, allow_unicode=True, width=sys.maxsize, default_flow_style=flow_style, sort_keys=False)


def select_field(msg, field: str | None):
    """``--field a.b``: the sub-value of a message; ValueError naming the missing part."""
    if not field:
        return msg
    value = msg
    for part in field.strip(".").split("."):
        if not hasattr(value, part):
            raise ValueError(f"invalid field '{field}': '{part}' is not a field of {type(value).__name__}")
        value = getattr(value, part)
    return value


def nest_parameters(values: dict) -> dict:
    """Dotted parameter names as nested dicts (``ros2 param dump``'s layout), keys sorted."""
    root: dict = {}
    for name in sorted(values):
        node = root
        parts = name.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = values[name]
    return root


def rate_stats(stamps: list[float]) -> dict | None:
    """Rate, min / max / std dev of the periods of the receive times in ``stamps`` (None if < 2)."""
    if len(stamps) < 2:
        return None
    periods = [b - a for a, b in zip(stamps, stamps[1:])]
    mean = sum(periods) / len(periods)
    std = math.sqrt(sum((p - mean) ** 2 for p in periods) / len(periods))
    return {"rate": 1.0 / mean if mean > 0 else 0.0, "min": min(periods), "max": max(periods), "std": std,
            "window": len(stamps)}


def format_rate(stats: dict) -> str:
    """One ``ros2 topic hz`` report."""
    return (f"average rate: {stats['rate']:.3f}\n\tmin: {stats['min']:.3f}s max: {stats['max']:.3f}s "
            f"std dev: {stats['std']:.5f}s window: {stats['window']}")


def choose_qos_policies(publishers: list[tuple[str, str]]) -> tuple[str, str]:
    """(reliability, durability) a subscriber should ask for to hear every publisher, from the publishers'
    (reliability, durability) names, as ros2cli does: reliable only if all publish reliably,
    transient_local only if all keep late-joiner history; with no publisher yet, reliable + volatile."""
    if not publishers:
        return "reliable", "volatile"
    reliability = "reliable" if all(r == "reliable" for r, _ in publishers) else "best_effort"
    durability = "transient_local" if all(d == "transient_local" for _, d in publishers) else "volatile"
    return reliability, durability


_PARAM_LABELS = {1: ("Boolean value is", None), 2: ("Integer value is", None), 3: ("Double value is", None),
                 4: ("String value is", None), 5: ("Byte values are", None), 6: ("Boolean values are", None),
                 7: ("Integer values are", None), 8: ("Double values are", None), 9: ("String values are", None)}


def format_param_value(type_id: int, value, hide_type: bool = False) -> str:
    """``ros2 param get``'s line for a rcl_interfaces ParameterValue type id and its Python value."""
    if type_id == 0:
        return "Parameter not set."
    if isinstance(value, (array.array, tuple)) or type(value).__name__ == "ndarray":
        value = list(value)
    if hide_type:
        return str(value)
    return f"{_PARAM_LABELS.get(type_id, ('Value is', None))[0]}: {value}"


def _interface_file(pkg: str, kind: str, name: str) -> Path:
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        share = get_package_share_directory(pkg)
    except PackageNotFoundError:
        raise ValueError(f"Unknown package '{pkg}'") from None
    path = Path(share) / kind / f"{name}.{kind}"
    if not path.is_file():
        raise ValueError(f"Could not find the interface '{pkg}/{kind}/{name}'")
    return path


def parse_interface_name(text: str) -> tuple[str, str, str]:
    """'pkg/msg/Name', 'pkg/srv/Name' or 'pkg/Name' (a message) -> (pkg, kind, Name)."""
    parts = text.strip("/").split("/")
    if len(parts) == 3 and parts[1] in ("msg", "srv", "action"):
        return parts[0], parts[1], parts[2]
    if len(parts) == 2:
        return parts[0], "msg", parts[1]
    raise ValueError(f"Invalid type '{text}': expected <package>/msg/<Name> or <package>/srv/<Name>")


def interface_text(type_name: str, *, comments: bool = True, all_comments: bool = False,
                   read=None, _indent: str = "") -> str:
    """``ros2 interface show``: the definition file, each field of a message type followed by that
    type's definition indented by a tab (without its comments unless ``all_comments``).
    ``read(pkg, kind, name) -> str`` returns a definition text (default: the ament index's file)."""
    from rosidl_adapter.parser import Type
    read = read or (lambda p, k, n: _interface_file(p, k, n).read_text())
    pkg, kind, name = parse_interface_name(type_name)
    lines = []
    for raw in read(pkg, kind, name).splitlines():
        code = raw.split("#", 1)[0].strip()
        shown = raw.rstrip() if (comments or all_comments) else raw.split("#", 1)[0].rstrip()
        if not shown and not code and not (comments or all_comments):
            continue
        if code == "---" or not code or "=" in code.split()[0] or " " not in code:
            lines.append(_indent + shown)
            continue
        fields = code.split()
        if "=" in fields[1] or (len(fields) > 2 and fields[2].startswith("=")):   # a constant
            lines.append(_indent + shown)
            continue
        lines.append(_indent + shown)
        t = Type(fields[0], context_package_name=pkg)
        if not t.is_primitive_type():
            lines.append(interface_text(f"{t.pkg_name}/msg/{t.type}", comments=all_comments,
                                        all_comments=all_comments, read=read, _indent=_indent + "\t").rstrip("\n"))
    return "\n".join(lines) + "\n"


def bag_info_text(path: str) -> str:
    """``ros2 bag info``: files, size, storage, duration, start/end, messages and each topic."""
    from rosbags.rosbag2 import Reader
    p = Path(path)
    import yaml
    meta_path = (p if p.is_dir() else p.parent) / "metadata.yaml"
    meta = (yaml.safe_load(meta_path.read_text()) or {}).get("rosbag2_bagfile_information", {}) \
        if meta_path.is_file() else {}
    with Reader(p) as reader:
        files = list(meta.get("relative_file_paths", [])) or [p.name]
        size = sum(f.stat().st_size for f in p.iterdir() if f.is_file()) if p.is_dir() else p.stat().st_size
        storage = meta.get("storage_identifier", "?")
        start, end = reader.start_time, reader.end_time
        if reader.message_count == 0:
            start = end = 0
        dur = max(0, end - start) / 1e9
        stamp = lambda ns: (f"{time.strftime('%b %d %Y %H:%M:%S', time.localtime(ns // 10**9))}.{ns % 10**9:09d} "
                            f"({ns // 10**9}.{ns % 10**9:09d})")
        out = [f"Files:             {', '.join(files)}",
               f"Bag size:          {_human_size(size)}",
               f"Storage id:        {storage}",
               f"ROS Distro:        {getattr(reader, 'ros_distro', None) or meta.get('ros_distro', 'unknown')}",
               f"Duration:          {dur:.9f}s",
               f"Start:             {stamp(start)}",
               f"End:               {stamp(end)}",
               f"Messages:          {reader.message_count}"]
        topics = sorted(reader.connections, key=lambda c: c.topic)
        label = "Topic information: "
        if not topics:
            out.append(label)
        for i, c in enumerate(topics):
            fmt = getattr(getattr(c, "ext", None), "serialization_format", "cdr")
            out.append(f"{label if i == 0 else ' ' * len(label)}Topic: {c.topic} | Type: {c.msgtype} | "
                       f"Count: {c.msgcount} | Serialization Format: {fmt}")
    return "\n".join(out) + "\n"


def _human_size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024


def _import_type(type_name: str):
    pkg, kind, name = parse_interface_name(type_name)
    try:
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ImportError, AttributeError):
        raise ValueError(f"The passed message type '{type_name}' is invalid") from None


# ----------------------------------------------------------------------------------------- the graph
#: the node name rmw gives an endpoint whose participant's node list has not arrived yet
_UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"


def wait_until_stable(snapshot, spin, *, stable_s: float, max_s: float, clock=time.monotonic) -> bool:
    """Discovery without a daemon: call ``spin(0.1)`` until ``snapshot()`` -> ``(state, complete)`` has
    returned the same state, complete, for ``stable_s`` seconds; at most ``max_s`` seconds. Processes of a
    running suite appear one by one, seconds apart on a loaded machine, so a short quiet spell is not the
    end of discovery. True when the graph settled, False when ``max_s`` ran out first."""
    start = clock()
    last, complete = snapshot()
    since = start
    while True:
        now = clock()
        if complete and now - since >= stable_s:
            return True
        if now - start >= max_s:
            return False
        spin(0.1)
        state, complete = snapshot()
        if state != last:
            last, since = state, clock()


class _Graph:
    """A hidden rclpy node in its own context, for one command."""

    def __init__(self, spin_time: float = 0.5, stable_s: float = 1.0, max_s: float = 5.0):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context)
        self.node = Node(f"_ros2cli_standin_{os.getpid()}", context=self.context, start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.spin(spin_time)
        self.settled = wait_until_stable(self._snapshot, self.spin, stable_s=stable_s, max_s=max_s)

    def _snapshot(self):
        """(the node, topic and service names, complete): complete is False while an endpoint belongs to a
        node not known yet (its process's node list, sent after its endpoints, has not arrived)."""
        topics = self.node.get_topic_names_and_types()
        unknown = any(i.node_name == _UNKNOWN_NODE
                      for name, _ in topics
                      for i in (*self.node.get_publishers_info_by_topic(name),
                                *self.node.get_subscriptions_info_by_topic(name)))
        return ((tuple(sorted(self.node.get_node_names_and_namespaces())), tuple(sorted(n for n, _ in topics)),
                 tuple(sorted(n for n, _ in self.node.get_service_names_and_types()))), not unknown)

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and self.context.ok():
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))

    def close(self) -> None:
        try:
            self.executor.shutdown()
            self.node.destroy_node()
        finally:
            self.context.try_shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def node_names(self) -> list[str]:
        return sorted(("/" + ns.strip("/") + "/" + n).replace("//", "/")
                      for n, ns in self.node.get_node_names_and_namespaces())

    def call(self, srv_type, name: str, request, timeout: float):
        client = self.node.create_client(srv_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                return None
            future = client.call_async(request)
            self.executor.spin_until_future_complete(future, timeout_sec=timeout)
            return future.result() if future.done() else None
        finally:
            self.node.destroy_client(client)


def _fq(node: str) -> str:
    return "/" + node.strip("/")


def _parser(prog: str, description: str) -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog=prog, description=f"{description} {NOTE}.")


def _verb(sub, name: str, help_text: str, description: str):
    """A verb's parser; its description ends with the stand-in label (every --help says what it is)."""
    return sub.add_parser(name, help=help_text, description=f"{description} {NOTE}.")


def _spin_arg(p, stable_s: float = 1.0):
    """The discovery flags; `stable_s`: the verb's default quiet spell (3 s for the lists, which must see every
    node; 1 s for the verbs that wait for the one topic or node they name)."""
    p.add_argument("--spin-time", type=float, default=0.5,
                   help="seconds to wait for discovery before looking at the graph (there is no daemon; default 0.5)")
    p.add_argument("--stable-time", type=float, default=stable_s,
                   help=f"(stand-in) then wait on until the nodes, topics and services have not changed for this "
                        f"many seconds and every endpoint's node is known (default {stable_s:g}; 0 = only until "
                        "every endpoint's node is known)")
    p.add_argument("--max-wait", type=float, default=15.0,
                   help="(stand-in) seconds the --stable-time wait may take at most (default 15)")
    p.add_argument("--no-daemon", action="store_true", help="accepted for compatibility (there is no daemon)")


def _graph(args) -> "_Graph":
    return _Graph(args.spin_time, stable_s=args.stable_time, max_s=args.max_wait)


# ----------------------------------------------------------------------------------------- verbs
def topic_main(argv) -> int:
    p = _parser("ros2 topic", "Various topic related sub-commands.")
    sub = p.add_subparsers(dest="verb", required=True, metavar="{list,echo,hz}")
    ls = _verb(sub, "list", "Output a list of available topics", "Output a list of available topics.")
    ls.add_argument("-t", "--show-types", action="store_true", help="Additionally show the topic type")
    ls.add_argument("-c", "--count-topics", action="store_true", help="Only display the number of topics discovered")
    ls.add_argument("--include-hidden-topics", action="store_true", help="Consider hidden topics as well")
    _spin_arg(ls, LIST_STABLE_S)
    ec = _verb(sub, "echo", "Output messages from a topic", "Output messages from a topic.")
    ec.add_argument("topic_name")
    ec.add_argument("message_type", nargs="?", help="Type of the ROS message (e.g. 'std_msgs/msg/String'); "
                                                    "taken from the graph when omitted")
    ec.add_argument("--once", action="store_true", help="Print the first message received and then exit")
    ec.add_argument("-n", "--max-count", type=int, default=0,
                    help="(stand-in) print this many messages, then exit (0 = until Ctrl-C)")
    ec.add_argument("--timeout", type=float, default=0.0,
                    help="(stand-in) give up with exit status 1 after this many seconds without the messages asked "
                         "for (0 = wait forever)")
    ec.add_argument("--field", help="Echo a selected field of a message, e.g. 'header.stamp'")
    ec.add_argument("-f", "--full-length", action="store_true", help="Output all elements for arrays/strings")
    ec.add_argument("-l", "--truncate-length", type=int, default=DEFAULT_TRUNCATE,
                    help=f"Length to truncate arrays and strings to (default {DEFAULT_TRUNCATE})")
    ec.add_argument("--no-arr", action="store_true", help="Don't print array fields of messages")
    ec.add_argument("--no-str", action="store_true", help="Don't print string fields of messages")
    ec.add_argument("--flow-style", action="store_true", help="Print collections in the block style, inline")
    ec.add_argument("--qos-depth", type=int, default=10, help="Queue size setting to subscribe with (default 10)")
    ec.add_argument("--qos-reliability", choices=("reliable", "best_effort"),
                    help="Reliability to subscribe with (default: what the publishers offer)")
    ec.add_argument("--qos-durability", choices=("volatile", "transient_local"),
                    help="Durability to subscribe with (default: what the publishers offer)")
    _spin_arg(ec)
    hz = _verb(sub, "hz", "Print the average publishing rate to screen",
               "Print the average receiving rate of a topic, once a second.")
    hz.add_argument("topic_name")
    hz.add_argument("-w", "--window", type=int, default=10000,
                    help="window size, in # of messages, for calculating rate (default 10000)")
    hz.add_argument("--reports", type=int, default=0,
                    help="(stand-in) exit after this many reports with a rate (0 = until Ctrl-C)")
    hz.add_argument("--timeout", type=float, default=0.0,
                    help="(stand-in) exit with status 1 if no report could be made within this many seconds "
                         "(0 = wait forever)")
    _spin_arg(hz)
    args = p.parse_args(argv)
    with _graph(args) as g:
        if args.verb == "list":
            return _topic_list(g, args)
        if args.verb == "echo":
            return _topic_echo(g, args)
        return _topic_hz(g, args)


def print_names_and_types(names_and_types, *, hidden: bool, count: bool, show_types: bool) -> int:
    """What ``ros2 topic list`` / ``ros2 service list`` print for [(name, [types])]."""
    shown = sorted((n, t) for n, t in names_and_types if hidden or not is_hidden_name(n))
    if count:
        print(len(shown))
        return 0
    for name, types in shown:
        print(f"{name} [{', '.join(types)}]" if show_types else name)
    return 0


def _topic_list(g, args) -> int:
    return print_names_and_types(g.node.get_topic_names_and_types(), hidden=args.include_hidden_topics,
                                 count=args.count_topics, show_types=args.show_types)


def _wait_topic_type(g, topic: str, timeout: float) -> str | None:
    end = time.monotonic() + timeout if timeout > 0 else math.inf
    warned = False
    while True:
        types = dict(g.node.get_topic_names_and_types()).get(topic)
        if types:
            return types[0]
        if time.monotonic() >= end or not g.context.ok():
            return None
        if not warned:
            print(f"WARNING: topic [{topic}] does not appear to be published yet", file=sys.stderr, flush=True)
            warned = True
        g.spin(0.1)


def _subscription_qos(g, topic: str, args, end: float = 0.0):
    """The subscriber QoS that hears the topic's publishers. Publishers are waited for until ``end``
    (a time.monotonic() value) unless both policies are given: a reliable subscription chosen before
    discovery never matches a best-effort publisher (what ``--timeout`` with an explicit type hit)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    while True:
        infos = g.node.get_publishers_info_by_topic(topic)
        if infos or (args.qos_reliability and args.qos_durability) or time.monotonic() >= end \
                or not g.context.ok():
            break
        g.spin(0.1)
    pubs = [(i.qos_profile.reliability.name.lower(), i.qos_profile.durability.name.lower()) for i in infos]
    reliability, durability = choose_qos_policies(pubs)
    return QoSProfile(depth=args.qos_depth,
                      reliability=ReliabilityPolicy[(args.qos_reliability or reliability).upper()],
                      durability=DurabilityPolicy[(args.qos_durability or durability).upper()])


def _topic_echo(g, args) -> int:
    topic = "/" + args.topic_name.lstrip("/")
    type_name = args.message_type
    if type_name is None:
        type_name = _wait_topic_type(g, topic, args.timeout)
        if type_name is None:
            print(f"Could not determine the type for the passed topic '{topic}'", file=sys.stderr)
            return 1
    try:
        msg_cls = _import_type(type_name)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 1
    wanted = 1 if args.once else max(0, args.max_count)
    truncate = None if args.full_length else args.truncate_length
    got = [0]

    def on_msg(msg):
        if wanted and got[0] >= wanted:
            return
        try:
            value = select_field(msg, args.field)
        except ValueError as exc:
            print(exc, file=sys.stderr)
            got[0] = -1
            return
        print(msg_to_yaml(value, truncate_length=truncate, no_arr=args.no_arr, no_str=args.no_str,
                          flow_style=args.flow_style), end="")
        print("---", flush=True)
        got[0] += 1

    end = time.monotonic() + args.timeout if args.timeout > 0 else math.inf
    g.node.create_subscription(msg_cls, topic, on_msg, _subscription_qos(g, topic, args, end))
    while g.context.ok() and got[0] >= 0 and not (wanted and got[0] >= wanted):
        if time.monotonic() >= end:
            print(f"ros2 topic echo: {got[0]} of {wanted or 'unbounded'} messages on {topic} within "
                  f"{args.timeout:g} s", file=sys.stderr)
            return 1
        g.executor.spin_once(timeout_sec=0.1)
    return 0 if got[0] >= 0 else 1


def _topic_hz(g, args) -> int:
    topic = "/" + args.topic_name.lstrip("/")
    type_name = _wait_topic_type(g, topic, args.timeout)
    if type_name is None:
        print(f"Could not determine the type for the passed topic '{topic}'", file=sys.stderr)
        return 1
    from collections import deque
    stamps: deque = deque(maxlen=max(2, args.window))
    fresh = [0]

    def on_msg(_raw):
        stamps.append(time.monotonic())
        fresh[0] += 1

    qos = _subscription_qos(g, topic, _HzQos(), time.monotonic() + 2.0)
    g.node.create_subscription(_import_type(type_name), topic, on_msg, qos,
                               raw=True)
    reports = 0
    start = next_report = time.monotonic() + 1.0
    while g.context.ok():
        g.executor.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        if now < next_report:
            continue
        next_report = now + 1.0
        stats = rate_stats(list(stamps)) if fresh[0] else None
        fresh[0] = 0
        if stats is None:
            print("no new messages", flush=True)
            if args.timeout > 0 and reports == 0 and now - start + 1.0 >= args.timeout:
                print(f"ros2 topic hz: no rate for {topic} within {args.timeout:g} s", file=sys.stderr)
                return 1
            continue
        print(format_rate(stats), flush=True)
        reports += 1
        if args.reports and reports >= args.reports:
            return 0
    return 0


class _HzQos:
    qos_depth, qos_reliability, qos_durability = 10, None, None


def service_main(argv) -> int:
    p = _parser("ros2 service", "Various service related sub-commands.")
    sub = p.add_subparsers(dest="verb", required=True, metavar="{list}")
    ls = _verb(sub, "list", "Output a list of available services", "Output a list of available services.")
    ls.add_argument("-t", "--show-types", action="store_true", help="Additionally show the service type")
    ls.add_argument("-c", "--count-services", action="store_true", help="Only display the number of services")
    ls.add_argument("--include-hidden-services", action="store_true", help="Consider hidden services as well")
    _spin_arg(ls, LIST_STABLE_S)
    args = p.parse_args(argv)
    with _graph(args) as g:
        services = g.node.get_service_names_and_types()
    return print_names_and_types(services, hidden=args.include_hidden_services, count=args.count_services,
                                 show_types=args.show_types)


def node_main(argv) -> int:
    p = _parser("ros2 node", "Various node related sub-commands.")
    sub = p.add_subparsers(dest="verb", required=True, metavar="{list}")
    ls = _verb(sub, "list", "Output a list of available nodes", "Output a list of available nodes.")
    ls.add_argument("-a", "--all", action="store_true", help="Display all nodes even hidden ones")
    ls.add_argument("-c", "--count-nodes", action="store_true", help="Only display the number of nodes discovered")
    _spin_arg(ls, LIST_STABLE_S)
    args = p.parse_args(argv)
    with _graph(args) as g:
        names = [n for n in g.node_names() if args.all or not is_hidden_name(n)]
    if args.count_nodes:
        print(len(names))
        return 0
    for name in names:
        print(name)
    return 0


def param_main(argv) -> int:
    p = _parser("ros2 param", "Various param related sub-commands.")
    sub = p.add_subparsers(dest="verb", required=True, metavar="{list,get,dump}")
    ls = _verb(sub, "list", "Output a list of available parameters", "Output a list of available parameters.")
    ls.add_argument("node_name", nargs="?", help="Name of the ROS node (all nodes if omitted)")
    ls.add_argument("--param-prefixes", nargs="+", default=[], help="Only list parameters with these prefixes")
    ls.add_argument("--param-type", action="store_true", help="Print parameter types with parameter names")
    ge = _verb(sub, "get", "Get parameter", "Get parameter.")
    ge.add_argument("node_name")
    ge.add_argument("parameter_name")
    ge.add_argument("--hide-type", action="store_true", help="Hide the type information")
    du = _verb(sub, "dump", "Show all of the parameters of a node in a YAML file format",
               "Show all of the parameters of a node in a YAML file format.")
    du.add_argument("node_name")
    for s in (ls, ge, du):
        s.add_argument("--timeout", type=float, default=10.0,
                       help="(stand-in) seconds to wait for the node's parameter services (default 10)")
        _spin_arg(s, LIST_STABLE_S if s is ls else 1.0)
    args = p.parse_args(argv)
    with _graph(args) as g:
        if args.verb == "list":
            nodes = [_fq(args.node_name)] if args.node_name else [n for n in g.node_names() if not is_hidden_name(n)]
            rc = 0
            for node in nodes:
                listed = _list_params(g, node, args.param_prefixes, args.timeout)
                if listed is None:
                    print("Node not found" if args.node_name else f"Exception while calling service of node "
                          f"'{node}'", file=sys.stderr)
                    rc = 1
                    continue
                if not args.node_name:
                    print(f"{node}:")
                types = _describe_types(g, node, listed, args.timeout) if args.param_type else {}
                for name in sorted(listed):
                    print(f"  {name}" + (f" (type: {types.get(name, '?')})" if args.param_type else ""))
            return rc
        node = _fq(args.node_name)
        names = [args.parameter_name] if args.verb == "get" else _list_params(g, node, [], args.timeout)
        values = None if names is None else _get_params(g, node, names, args.timeout)
        if values is None:
            print("Node not found", file=sys.stderr)
            return 1
        if args.verb == "get":
            (type_id, value), = values.values()
            print(format_param_value(type_id, value, args.hide_type))
            return 0 if type_id else 1
        import yaml
        doc = {node: {"ros__parameters": nest_parameters({k: v for k, (t, v) in values.items() if t})}}
        print(yaml.dump(_yaml_plain(doc), default_flow_style=False, sort_keys=False), end="")
        return 0


def _yaml_plain(value):
    if isinstance(value, dict):
        return {k: _yaml_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, array.array)) or type(value).__name__ == "ndarray":
        return [_yaml_plain(v) for v in value]
    return value.item() if hasattr(value, "item") and not isinstance(value, (str, bytes)) else value


def _list_params(g, node: str, prefixes, timeout):
    from rcl_interfaces.srv import ListParameters
    req = ListParameters.Request(prefixes=list(prefixes), depth=0)
    res = g.call(ListParameters, f"{node}/list_parameters", req, timeout)
    return None if res is None else list(res.result.names)


def _get_params(g, node: str, names, timeout):
    from rcl_interfaces.srv import GetParameters
    from rclpy.parameter import parameter_value_to_python
    res = g.call(GetParameters, f"{node}/get_parameters", GetParameters.Request(names=list(names)), timeout)
    if res is None:
        return None
    out = {n: (0, None) for n in names}          # a node answers no value at all for an undeclared name
    out.update({n: (v.type, parameter_value_to_python(v) if v.type else None) for n, v in zip(names, res.values)})
    return out


def _describe_types(g, node: str, names, timeout) -> dict:
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import DescribeParameters
    res = g.call(DescribeParameters, f"{node}/describe_parameters", DescribeParameters.Request(names=list(names)),
                 timeout)
    kinds = {getattr(ParameterType, k): k[len("PARAMETER_"):].lower() for k in dir(ParameterType)
             if k.startswith("PARAMETER_") and isinstance(getattr(ParameterType, k), int)}
    return {} if res is None else {d.name: kinds.get(d.type, "?") for d in res.descriptors}


def interface_main(argv) -> int:
    p = _parser("ros2 interface", "Show information about ROS interfaces.")
    sub = p.add_subparsers(dest="verb", required=True, metavar="{show}")
    sh = _verb(sub, "show", "Output the interface definition",
               "Output the interface definition, nested types expanded.")
    sh.add_argument("type", help="Show an interface definition (e.g. 'comper_msgs/msg/EpisodeSummary')")
    sh.add_argument("--all-comments", action="store_true", help="Show all comments, including for nested types")
    sh.add_argument("--no-comments", action="store_true", help="Show no comments or whitespace")
    args = p.parse_args(argv)
    try:
        text = interface_text(args.type, comments=not args.no_comments, all_comments=args.all_comments)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 1
    print(text, end="")
    return 0


def bag_main(argv) -> int:
    p = _parser("ros2 bag", "Various rosbag related sub-commands (read with rosbags).")
    sub = p.add_subparsers(dest="verb", required=True, metavar="{info}")
    inf = _verb(sub, "info", "Print information about a bag to the screen",
                "Print information about a bag (a rosbag2 directory).")
    inf.add_argument("bag_path", help="Bag to open")
    args = p.parse_args(argv)
    if not Path(args.bag_path).exists():
        print(f"[ERROR] [ros2bag]: bag path '{args.bag_path}' does not exist", file=sys.stderr)
        return 1
    try:
        print(bag_info_text(args.bag_path), end="")
    except Exception as exc:     # not a bag, unreadable metadata: one line, as ros2 bag info
        print(f"[ERROR] [ros2bag]: cannot read {args.bag_path}: {exc}", file=sys.stderr)
        return 1
    return 0


_MAINS = {"topic": topic_main, "service": service_main, "node": node_main, "param": param_main,
          "interface": interface_main, "bag": bag_main}


def main(argv: list[str]) -> int:
    """``ros2 <verb> ...`` for the verbs in VERBS; Ctrl-C ends a running echo / hz with status 0."""
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)          # `ros2 topic echo ... | head` ends quietly
    try:
        return _MAINS[argv[0]](argv[1:])
    except KeyboardInterrupt:
        return 0
