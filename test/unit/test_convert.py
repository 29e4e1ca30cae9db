"""The numpy <-> message conversions (comper_msgs_py.convert) and batch validation."""
import numpy as np
import pytest

from comper_msgs.msg import Array
from comper_msgs_py.arrays import TransitionError, Transitions
from comper_msgs_py.convert import (array_to_numpy, batch_to_transitions, numpy_to_array,
                                    transitions_to_batch)


def _mujoco(n=5, obs=11, act=3, rng=np.random.default_rng(0)):
    return Transitions(states=rng.normal(size=(n, obs)).astype(np.float32),
                       actions=rng.uniform(-1, 1, (n, act)).astype(np.float32),
                       rewards=rng.normal(size=n).astype(np.float32),
                       next_states=rng.normal(size=(n, obs)).astype(np.float32),
                       terminated=np.array([0, 0, 1, 0, 0], bool), truncated=np.array([0, 0, 0, 0, 1], bool))


def test_array_roundtrip_keeps_dtype_and_shape():
    for arr in (np.arange(24, dtype=np.float32).reshape(2, 3, 4), np.arange(12, dtype=np.uint8).reshape(3, 4),
                np.float32(2.5), np.zeros((0, 7), np.float32)):
        back = array_to_numpy(numpy_to_array(arr))
        assert back.dtype == np.asarray(arr).dtype and back.shape == np.asarray(arr).shape
        np.testing.assert_array_equal(back, arr)


def test_array_with_wrong_size_is_refused():
    msg = numpy_to_array(np.zeros((2, 3), np.float32))
    msg.shape = [4, 3]
    with pytest.raises(TransitionError, match="needs 12 values"):
        array_to_numpy(msg)


def test_uint8_frames_are_not_widened():
    msg = numpy_to_array(np.zeros((84, 84), np.uint8))
    assert msg.dtype == Array.DTYPE_UINT8 and len(msg.data_u8) == 84 * 84 and len(msg.data_f32) == 0


def test_batch_roundtrip_keeps_terminated_and_truncated_apart():
    t = _mujoco()
    back = batch_to_transitions(transitions_to_batch(t))
    np.testing.assert_array_equal(back.terminated, t.terminated)
    np.testing.assert_array_equal(back.truncated, t.truncated)
    np.testing.assert_array_equal(back.states, t.states)
    assert back.value_labels.size == 0


@pytest.mark.parametrize("mutate, match", [
    (lambda t: setattr(t, "rewards", np.zeros(4, np.float32)), "leading dimension"),
    (lambda t: setattr(t, "next_states", np.zeros((5, 12), np.float32)), "differ in shape"),
    (lambda t: t.states.__setitem__((1, 2), np.nan), "NaN or Inf"),
    (lambda t: setattr(t, "value_labels", np.zeros(3, np.float32)), "value_labels"),
])
def test_validation_names_the_problem(mutate, match):
    t = _mujoco()
    mutate(t)
    with pytest.raises(TransitionError, match=match):
        t.validate()


def test_declare_config_accepts_integers_for_floats_and_refuses_bad_values():
    """`-p delta:=0` must work for a float parameter; out-of-range values are refused clearly."""
    from dataclasses import dataclass

    import rclpy
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from comper_msgs_py.params import ConfigError, param
    from comper_msgs_py.ros_params import declare_config

    @dataclass(frozen=True)
    class Cfg:
        delta: float = param(1e-4, "threshold", minimum=0.0)
        mode: str = param("a", "mode", choices=("a", "b"))

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = Node("cfg_ok", context=ctx, parameter_overrides=[Parameter("delta", value=0)])
        cfg = declare_config(node, Cfg)
        assert cfg.delta == 0.0 and isinstance(cfg.delta, float) and cfg.mode == "a"
        desc = node.describe_parameter("delta")
        assert "threshold" in desc.description and desc.read_only
        bad = Node("cfg_bad", context=ctx, parameter_overrides=[Parameter("mode", value="c")])
        with pytest.raises(ConfigError, match="not one of"):
            declare_config(bad, Cfg)
    finally:
        ctx.try_shutdown()
