"""Typed parameters from config dataclasses: declared, validated, refused with the key named."""

from dataclasses import dataclass

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from terrain_perception.config import load_config, make_config, param
from terrain_ros.params import declare_config


@dataclass(frozen=True)
class DemoConfig:
    window_px: int = param(9, 'block size', 5, 51)
    threshold_m: float = param(0.02, 'cost threshold', 0.0, 1.0)
    enabled: bool = param(True, 'switch')
    mode: str = param('walk', 'gait', choices=('walk', 'trot'))
    weights: tuple = param((1.0, 2.0), 'weights')


def _node(ctx, overrides=()):
    return Node('param_demo', context=ctx, parameter_overrides=list(overrides))


def test_declares_every_field_with_description_and_range(ros_context):
    node = _node(ros_context)
    cfg = declare_config(node, DemoConfig)
    assert cfg == DemoConfig()
    desc = node.describe_parameter('window_px')
    assert desc.description == 'block size'
    assert desc.integer_range[0].from_value == 5 and desc.integer_range[0].to_value == 51
    assert node.describe_parameter('threshold_m').floating_point_range[0].to_value == 1.0
    node.destroy_node()


def test_overrides_are_applied(ros_context):
    node = _node(ros_context, [Parameter('window_px', value=15),
                               Parameter('weights', value=[3.0, 4.0])])
    cfg = declare_config(node, DemoConfig)
    assert cfg.window_px == 15 and cfg.weights == (3.0, 4.0)
    node.destroy_node()


@pytest.mark.parametrize('override', [
    Parameter('window_px', value=99),          # out of range
    Parameter('window_px', value='nine'),      # wrong type
    Parameter('threshold_m', value=-0.5),      # out of range
    Parameter('mode', value='gallop'),         # not a choice
])
def test_bad_override_is_refused_naming_the_key(ros_context, override):
    node = _node(ros_context, [override])
    with pytest.raises(ValueError, match=override.name):
        declare_config(node, DemoConfig)
    node.destroy_node()


def test_runtime_set_is_checked_and_reported(ros_context):
    node = _node(ros_context)
    seen = []
    declare_config(node, DemoConfig, on_change=seen.append)
    bad = node.set_parameters([Parameter('threshold_m', value=5.0)])[0]
    assert not bad.successful and 'threshold_m' in bad.reason
    assert node.get_parameter('threshold_m').value == 0.02
    ok = node.set_parameters([Parameter('threshold_m', value=0.05)])[0]
    assert ok.successful and seen[-1].threshold_m == 0.05
    node.destroy_node()


def test_core_config_from_mapping_and_yaml(tmp_path):
    with pytest.raises(ValueError, match='window_px'):
        make_config(DemoConfig, {'window_px': 2})
    with pytest.raises(ValueError, match='unknown parameter'):
        make_config(DemoConfig, {'windowpx': 9})
    path = tmp_path / 'demo.yaml'
    path.write_text('demo:\n  ros__parameters:\n    window_px: 21\n    threshold_m: 0.1\n')
    assert load_config(DemoConfig, path, 'demo') == DemoConfig(window_px=21, threshold_m=0.1)
