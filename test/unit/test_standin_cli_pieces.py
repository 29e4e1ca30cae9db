"""The pure pieces of the ros2 stand-in's inspection verbs (comper_agent.tools.ros2_cli): message printing
through rosidl introspection, parameter nesting, rate statistics, QoS choice, interface texts.
No ROS graph (the verbs against running nodes: test/integration/test_standin_cli.py)."""
import array

import pytest
import yaml

from comper_agent.tools import ros2_cli as cli


def test_hidden_names_follow_ros2cli():
    assert cli.is_hidden_name("/_ros2cli_standin_1")
    assert cli.is_hidden_name("/ns/_private/topic")
    assert not cli.is_hidden_name("/sim_node/episodes")


def test_message_yaml_keeps_field_order_nested_messages_and_arrays():
    from comper_msgs.msg import EpisodeSummary, Array
    msg = EpisodeSummary(run_id="r1", env_id="Hopper-v4", source="train", episode_id=7, episode_return=12.5,
                         length=30, terminated=True)
    msg.header.frame_id = "f"
    msg.header.stamp.sec = 3
    doc = yaml.safe_load(cli.msg_to_yaml(msg))
    assert list(doc) == list(EpisodeSummary.get_fields_and_field_types())
    assert doc["header"] == {"stamp": {"sec": 3, "nanosec": 0}, "frame_id": "f"}
    assert doc["episode_id"] == 7 and doc["episode_return"] == 12.5 and doc["terminated"] is True
    arr = Array(dtype=Array.DTYPE_UINT8, shape=[2, 3], data_u8=bytes(range(6)))
    plain = cli.msg_to_plain(arr, truncate_length=4)
    assert plain["shape"] == [2, 3] and plain["data_u8"] == [0, 1, 2, 3, "..."] and plain["data_f32"] == []
    assert cli.msg_to_plain(arr, truncate_length=None)["data_u8"] == [0, 1, 2, 3, 4, 5]


def test_truncation_no_arr_no_str_and_field_selection():
    from std_msgs.msg import Float32MultiArray, String
    m = Float32MultiArray(data=[float(i) for i in range(200)])
    assert len(cli.msg_to_plain(m)["data"]) == cli.DEFAULT_TRUNCATE + 1
    assert cli.msg_to_plain(m, truncate_length=None)["data"][-1] == 199.0
    assert cli.msg_to_plain(m, no_arr=True)["data"] == "<array type: sequence<float>>"
    assert cli.msg_to_plain(String(data="x" * 300), truncate_length=5)["data"] == "xxxxx..."
    assert cli.msg_to_plain(String(data="abc"), no_str=True)["data"] == "<string length: <3>>"
    assert cli.msg_to_yaml(cli.select_field(m, "layout.data_offset")) == "0\n"
    with pytest.raises(ValueError, match="'nope' is not a field"):
        cli.select_field(m, "layout.nope")


def test_parameter_nesting_and_values_print_like_ros2cli():
    nested = cli.nest_parameters({"use_sim_time": False, "qos_overrides./a.publisher.depth": 10,
                                  "qos_overrides./a.publisher.history": "keep_last", "delta": 0.5})
    assert nested == {"delta": 0.5, "qos_overrides": {"/a": {"publisher": {"depth": 10, "history": "keep_last"}}},
                      "use_sim_time": False}
    assert cli.format_param_value(4, "Hopper-v4") == "String value is: Hopper-v4"
    assert cli.format_param_value(2, 5) == "Integer value is: 5"
    assert cli.format_param_value(3, 0.5, hide_type=True) == "0.5"
    assert cli.format_param_value(8, array.array("d", [1.0, 2.0])) == "Double values are: [1.0, 2.0]"
    assert cli.format_param_value(0, None) == "Parameter not set."


def test_rate_statistics_of_receive_times():
    assert cli.rate_stats([1.0]) is None
    s = cli.rate_stats([0.0, 0.1, 0.2, 0.3, 0.5])
    assert s["window"] == 5 and s["min"] == pytest.approx(0.1) and s["max"] == pytest.approx(0.2)
    assert s["rate"] == pytest.approx(8.0)
    text = cli.format_rate(s)
    assert text.startswith("average rate: 8.000\n\tmin: 0.100s max: 0.200s std dev: ") and text.endswith("window: 5")


def test_qos_choice_hears_every_publisher():
    assert cli.choose_qos_policies([]) == ("reliable", "volatile")
    assert cli.choose_qos_policies([("reliable", "transient_local")]) == ("reliable", "transient_local")
    assert cli.choose_qos_policies([("reliable", "volatile"), ("best_effort", "transient_local")]) == \
        ("best_effort", "volatile")


def test_interface_text_expands_nested_types_without_their_comments():
    defs = {("p", "msg", "Outer"): "# top comment\nInner a   # the inner\nint32 X=3\nfloat64[] b\n",
            ("p", "msg", "Inner"): "# inner comment\nstring name  # its name\n",
            ("p", "srv", "Do"): "Inner req\n---\nbool ok\n"}
    read = lambda p, k, n: defs[(p, k, n)]
    assert cli.interface_text("p/msg/Outer", read=read) == (
        "# top comment\nInner a   # the inner\n\tstring name\nint32 X=3\nfloat64[] b\n")
    assert cli.interface_text("p/msg/Outer", comments=False, read=read) == (
        "Inner a\n\tstring name\nint32 X=3\nfloat64[] b\n")
    assert cli.interface_text("p/Outer", all_comments=True, read=read).splitlines()[2:4] == [
        "\t# inner comment", "\tstring name  # its name"]
    assert cli.interface_text("p/srv/Do", read=read) == "Inner req\n\tstring name\n---\nbool ok\n"
    with pytest.raises(ValueError, match="Invalid type"):
        cli.interface_text("justaname", read=read)


def test_interface_text_of_an_installed_message_and_an_unknown_one():
    text = cli.interface_text("comper_msgs/msg/EpisodeSummary")
    assert "std_msgs/Header header" in text and "\tbuiltin_interfaces/Time stamp" in text
    assert "\t\tint32 sec" in text and "# gymnasium id" in text
    with pytest.raises(ValueError, match="Could not find the interface"):
        cli.interface_text("comper_msgs/msg/NoSuchThing")
    with pytest.raises(ValueError, match="Unknown package"):
        cli.interface_text("no_such_pkg/msg/X")
