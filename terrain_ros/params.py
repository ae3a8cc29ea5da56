"""ROS parameters declared from the core's typed config dataclasses.

One call per config::

    self.stereo_cfg = declare_config(self, StereoConfig)

declares every field of the frozen dataclass as a ROS parameter with its typed default, its
description and its range (``terrain_perception.config.param`` metadata), refuses wrong-typed or
out-of-range values with a reason naming the key (at start-up *and* at runtime: one check, the
same set-callback), and returns the dataclass rebuilt from the parameter values. A runtime change
calls ``on_change(new_config)`` after it was accepted.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional, Type, TypeVar

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter

from terrain_perception.config import check_value

C = TypeVar('C')


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    raise ValueError(f'config field {f.name!r} has no default')


def _ros_default(value: Any) -> Any:
    # ROS parameters know lists, not tuples.
    return list(value) if isinstance(value, tuple) else value


def _descriptor(f: dataclasses.Field, full_name: str, value: Any) -> ParameterDescriptor:
    meta = f.metadata or {}
    desc = ParameterDescriptor(name=full_name, description=str(meta.get('description', '')))
    lo, hi = meta.get('range', (None, None))
    if lo is not None and hi is not None and not isinstance(value, bool):
        if isinstance(value, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        elif isinstance(value, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
    elif lo is not None or hi is not None:
        desc.additional_constraints = f'range [{lo}, {hi}]'
    if meta.get('choices'):
        desc.additional_constraints = f'one of {list(meta["choices"])}'
    return desc


def _name(prefix: str, field_name: str) -> str:
    return f'{prefix}.{field_name}' if prefix else field_name


def current_config(node: Node, cls: Type[C], prefix: str = '') -> C:
    """The config dataclass rebuilt from the node's current parameter values."""
    values = {}
    for f in dataclasses.fields(cls):
        v = node.get_parameter(_name(prefix, f.name)).value
        default = _default(f)
        if isinstance(default, tuple):
            v = tuple(v)
        values[f.name] = v
    return cls(**values)


def declare_config(node: Node, cls: Type[C], prefix: str = '',
                   on_change: Optional[Callable[[C], None]] = None) -> C:
    """Declare ``cls``'s fields as parameters of ``node`` and return the resulting config.

    Raises:
        ValueError: an override (from YAML or ``parameter_overrides``) has the wrong type or is
            out of range; the message names the key.
    """
    fields = {_name(prefix, f.name): f for f in dataclasses.fields(cls)}

    def check(params: list[Parameter]) -> SetParametersResult:
        reasons = []
        for p in params:
            f = fields.get(p.name)
            if f is None:
                continue
            try:
                value = p.value
                if isinstance(_default(f), float) and isinstance(value, int) \
                        and not isinstance(value, bool):
                    value = float(value)
                check_value(cls, f.name, value)
            except ValueError as exc:
                reasons.append(f'parameter {p.name!r}: {exc}')
        if reasons:
            return SetParametersResult(successful=False, reason='; '.join(reasons))
        return SetParametersResult(successful=True)

    # Registered before declaring, so start-up overrides and runtime sets share one check.
    node.add_on_set_parameters_callback(check)
    for full, f in fields.items():
        default = _ros_default(_default(f))
        try:
            node.declare_parameter(full, default, _descriptor(f, full, default))
        except (ParameterException, TypeError) as exc:
            raise ValueError(f'{node.get_name()}: parameter {full!r} refused: {exc}') from exc
        except Exception as exc:  # rclpy raises its own types for type/range violations
            if type(exc).__name__.startswith('InvalidParameter'):
                raise ValueError(f'{node.get_name()}: parameter {full!r} refused: {exc}') from exc
            raise
    config = current_config(node, cls, prefix)

    if on_change is not None:
        def after(params: list[Parameter]) -> None:
            if any(p.name in fields for p in params):
                on_change(current_config(node, cls, prefix))
        node.add_post_set_parameters_callback(after)
    return config
