"""The ros2 stand-in's inspection verbs against the running suite: two sim_nodes, a memory_node and a
qt_trainer_node started with `ros2 run` in their own processes, then `ros2 topic|service|node|param|interface|bag
...` run as subprocesses, as a user types them. Where a real ros2cli is on PATH (setup.sh then leaves the stand-in
off PATH) the stand-in itself is still what is tested: it is called by its path."""
import os
import subprocess
import sys
import time

import pytest
import yaml

from conftest import ROOT, NodeProcess

STANDIN = str(ROOT / "scripts" / "ros2-standin" / "ros2")
TASK = "InvertedPendulum-v4"
TAG = os.getpid()
SIM, MEM, QT, SIM2 = f"sim_cli{TAG}", f"mem_cli{TAG}", f"qt_cli{TAG}", f"sim2_cli{TAG}"
#: a service of each node of the suite
SERVICES = {SIM: f"/{SIM}/step", MEM: f"/{MEM}/store", QT: f"/{QT}/reduce", SIM2: f"/{SIM2}/step"}


def ros2(*args, timeout=120, check=True):
    res = subprocess.run([sys.executable, STANDIN, *args], capture_output=True, text=True, timeout=timeout)
    if check:
        assert res.returncode == 0, f"ros2 {' '.join(args)} -> {res.returncode}\n{res.stdout}\n{res.stderr}"
    return res


def until(args, ok, wait_s=90):
    """Run the list command until its output satisfies ok (freshly started nodes take a while to come up). Each try
    waits for a 1 s quiet spell only: these checks are of the output's form; that one call with the default wait
    finds every node is test_node_and_service_list_find_every_node_of_the_suite_each_time's."""
    deadline = time.monotonic() + wait_s
    while True:
        res = ros2(*args, "--stable-time", "1", check=False)
        if res.returncode == 0 and ok(res.stdout):
            return res.stdout
        if time.monotonic() > deadline:
            pytest.fail(f"ros2 {' '.join(args)} never gave the expected output:\n{res.stdout}\n{res.stderr}")
        time.sleep(0.5)


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    log_dir = tmp_path_factory.mktemp("nodes")
    procs = [NodeProcess("comper_sim", "sim_node", "--ros-args", "-p", f"env_id:={TASK}", "-r", f"__node:={SIM}",
                         log_dir=log_dir, name=SIM),
             NodeProcess("comper_memory", "memory_node", "--ros-args", "-p", "stats_period_s:=0.2",
                         "-r", f"__node:={MEM}", log_dir=log_dir, name=MEM),
             NodeProcess("comper_agent", "qt_trainer_node", "--ros-args", "-p", f"memory_node:={MEM}",
                         "-r", f"__node:={QT}", log_dir=log_dir, name=QT),
             NodeProcess("comper_sim", "sim_node", "--ros-args", "-p", f"env_id:={TASK}", "-r", f"__node:={SIM2}",
                         log_dir=log_dir, name=SIM2)]
    try:
        # the processes take a while to start: wait until the lists show them once
        until(["node", "list"], lambda out: {f"/{n}" for n in SERVICES} <= set(out.split()))
        until(["service", "list"], lambda out: set(SERVICES.values()) <= set(out.split()))
        until(["topic", "list"], lambda out: f"/{SIM}/episodes" in out and f"/{MEM}/stats" in out)
        yield procs
    finally:
        for p in procs:
            p.stop()


def test_help_says_it_is_the_stand_in():
    assert "stand-in" in ros2("--help").stdout
    for verb in (["topic", "echo"], ["topic", "list"], ["topic", "hz"], ["service", "list"], ["node", "list"],
                 ["param", "get"], ["param", "dump"], ["param", "list"], ["interface", "show"], ["bag", "info"]):
        assert "[stand-in]" in ros2(*verb, "--help").stdout, verb


# Without a daemon each call discovers the graph afresh: a list waits until the graph has not changed for
# --stable-time (3 s) and every endpoint's node is known, so one call shows every node of a running suite.

@pytest.mark.slow      # ten list calls, each waiting out its quiet spell (~40 s)
def test_node_and_service_list_find_every_node_of_the_suite_each_time(suite):
    """Five rounds, each a `node list` and a `service list` run at once (each sees the other's hidden node come
    and go): every call shows all four nodes, and a service of each, the first time."""
    nodes = {f"/{n}" for n in SERVICES}
    for _ in range(5):
        calls = [subprocess.Popen([sys.executable, STANDIN, verb, "list"], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for verb in ("node", "service")]
        (node_out, node_err), (service_out, service_err) = (c.communicate(timeout=120) for c in calls)
        assert [c.returncode for c in calls] == [0, 0], node_err + service_err
        assert nodes <= set(node_out.split()), node_out
        assert set(SERVICES.values()) <= set(service_out.split()), service_out


def test_node_list_shows_the_nodes_and_hides_hidden_ones(suite):
    names = until(["node", "list"], lambda out: f"/{SIM}" in out.split() and f"/{MEM}" in out.split()).split()
    assert not any("_ros2cli_standin" in n for n in names)
    assert any(n.startswith("/_ros2cli_standin_") for n in ros2("node", "list", "-a").stdout.split())
    assert int(until(["node", "list", "-c"], lambda out: int(out) >= 2)) >= 2


def test_topic_and_service_list_with_types(suite):
    stats = f"/{MEM}/stats [comper_msgs/msg/MemoryStats]"
    episodes = f"/{SIM}/episodes [comper_msgs/msg/EpisodeSummary]"
    until(["topic", "list", "-t"], lambda out: stats in out.splitlines() and episodes in out.splitlines())
    until(["topic", "list"], lambda out: f"/{MEM}/stats" in out.split() and "[" not in out)
    assert int(until(["topic", "list", "-c"], lambda out: int(out) >= 2)) >= 2
    step, store = f"/{SIM}/step [comper_msgs/srv/Step]", f"/{MEM}/store [comper_msgs/srv/Store]"
    params = f"/{SIM}/get_parameters [rcl_interfaces/srv/GetParameters]"
    until(["service", "list", "--show-types"], lambda out: {step, store, params} <= set(out.splitlines()))
    hidden = until(["service", "list", "--include-hidden-services"], lambda out: f"/{SIM}/step" in out.split())
    assert not any(line.startswith("[") for line in hidden.splitlines())


def test_topic_echo_once_and_bounded(suite):
    from comper_msgs.msg import MemoryStats
    out = ros2("topic", "echo", f"/{MEM}/stats", "--once", "--timeout", "60").stdout
    doc, = [d for d in yaml.safe_load_all(out) if d is not None]
    assert list(doc) == list(MemoryStats.get_fields_and_field_types())
    assert doc["transitions_stored"] == 0 and doc["rtm_size"] == 0 and set(doc["header"]) == {"stamp", "frame_id"}
    out = ros2("topic", "echo", f"/{MEM}/stats", "comper_msgs/msg/MemoryStats", "-n", "3", "--field",
               "header.stamp", "--timeout", "60").stdout
    stamps = [d for d in yaml.safe_load_all(out) if d is not None]
    assert len(stamps) == 3 and all(set(s) == {"sec", "nanosec"} for s in stamps)
    assert stamps[0]["sec"] * 10**9 + stamps[0]["nanosec"] < stamps[2]["sec"] * 10**9 + stamps[2]["nanosec"]
    bad = ros2("topic", "echo", f"/{MEM}/stats", "--once", "--field", "nope", "--timeout", "60", check=False)
    assert bad.returncode == 1 and "'nope' is not a field" in bad.stderr


def test_topic_hz_reports_a_rate_and_stops(suite):
    out = ros2("topic", "hz", f"/{MEM}/stats", "--reports", "2", "--window", "50", "--timeout", "60").stdout
    reports = [line for line in out.splitlines() if line.startswith("average rate:")]
    assert len(reports) == 2
    assert all(float(r.split(":")[1]) > 0 for r in reports)
    assert "window:" in out


def test_param_get_list_and_dump(suite):
    assert ros2("param", "get", f"/{SIM}", "env_id").stdout.strip() == f"String value is: {TASK}"
    assert ros2("param", "get", SIM, "env_id", "--hide-type").stdout.strip() == TASK
    assert ros2("param", "get", f"/{MEM}", "stats_period_s").stdout.strip() == "Double value is: 0.2"
    missing = ros2("param", "get", f"/{SIM}", "no_such_parameter", check=False)
    assert missing.returncode == 1 and missing.stdout.strip() == "Parameter not set."
    listed = ros2("param", "list", f"/{SIM}").stdout.splitlines()
    assert "  env_id" in listed and "  use_sim_time" in listed
    assert "  env_id (type: string)" in ros2("param", "list", f"/{SIM}", "--param-type").stdout.splitlines()
    dump = yaml.safe_load(ros2("param", "dump", f"/{SIM}").stdout)
    params = dump[f"/{SIM}"]["ros__parameters"]
    assert params["env_id"] == TASK and params["use_sim_time"] is False
    gone = ros2("param", "get", "/no_such_node", "x", "--timeout", "1", check=False)
    assert gone.returncode == 1 and "Node not found" in gone.stderr


def test_interface_show_of_suite_types():
    out = ros2("interface", "show", "comper_msgs/srv/Step").stdout
    assert "---" in out.splitlines()
    summary = ros2("interface", "show", "comper_msgs/msg/EpisodeSummary").stdout.splitlines()
    assert summary[summary.index("std_msgs/Header header") + 1] == "\tbuiltin_interfaces/Time stamp"
    bad = ros2("interface", "show", "comper_msgs/msg/Nope", check=False)
    assert bad.returncode == 1 and "Could not find the interface" in bad.stderr


def test_bag_info_of_a_recorded_run(tmp_path):
    from scaffolding import synthetic_run, write_run_bag
    t, summaries = synthetic_run(300, seed=2, run_id="cli")
    bag = write_run_bag(tmp_path / "bag", t, summaries)
    out = ros2("bag", "info", str(bag)).stdout
    lines = out.splitlines()
    assert lines[2].split() == ["Storage", "id:", "mcap"]
    assert f"Messages:          {2 * len(summaries)}" in lines
    assert any(f"Topic: /comcact_node/episodes | Type: comper_msgs/msg/EpisodeSummary | Count: {len(summaries)} "
               "| Serialization Format: cdr" in line for line in lines)
    missing = ros2("bag", "info", str(tmp_path / "none"), check=False)
    assert missing.returncode == 1 and "does not exist" in missing.stderr
