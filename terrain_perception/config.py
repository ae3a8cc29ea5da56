"""Typed configuration: frozen dataclasses whose fields carry a description and a range.

Every algorithm takes one frozen dataclass. Fields are declared with :func:`param`, which the
ROS side (``terrain_ros.params``) turns into declared, typed, range-checked ROS parameters and
which :func:`load_config` reads from the YAML files in ``config/``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping, Optional, Type, TypeVar

C = TypeVar('C')


def param(default: Any, description: str, lo: Optional[float] = None,
          hi: Optional[float] = None, choices: Optional[tuple] = None):
    """A dataclass field with a description, an optional [lo, hi] range and allowed choices."""
    meta = {'description': description, 'range': (lo, hi), 'choices': choices}
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def check_value(cls: Type, name: str, value: Any) -> Any:
    """Validate and coerce one field value; raise ValueError naming the key on a bad one."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if name not in fields:
        raise ValueError(f'{cls.__name__}: unknown parameter {name!r} '
                         f'(known: {", ".join(sorted(fields))})')
    f = fields[name]
    default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    typ = type(default)
    if typ is bool:
        if not isinstance(value, bool):
            raise ValueError(f'{cls.__name__}.{name} must be a bool, got {value!r}')
    elif typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f'{cls.__name__}.{name} must be an integer, got {value!r}')
    elif typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f'{cls.__name__}.{name} must be a number, got {value!r}')
        value = float(value)
    elif typ is str:
        if not isinstance(value, str):
            raise ValueError(f'{cls.__name__}.{name} must be a string, got {value!r}')
    elif typ in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ValueError(f'{cls.__name__}.{name} must be a list, got {value!r}')
        value = typ(value)
    lo, hi = f.metadata.get('range', (None, None)) if f.metadata else (None, None)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ValueError(f'{cls.__name__}.{name} = {value} is outside its range '
                             f'[{lo}, {hi}]')
    choices = f.metadata.get('choices') if f.metadata else None
    if choices and value not in choices:
        raise ValueError(f'{cls.__name__}.{name} = {value!r} is not one of {list(choices)}')
    return value


def make_config(cls: Type[C], values: Optional[Mapping[str, Any]] = None) -> C:
    """Build ``cls`` from a mapping, checking every key's type and range."""
    values = dict(values or {})
    checked = {k: check_value(cls, k, v) for k, v in values.items()}
    return cls(**checked)


def load_config(cls: Type[C], path: 'str | Path', key: str) -> C:
    """Read ``key``'s parameters from a ROS-style YAML file (``key: ros__parameters: {...}``)."""
    import yaml
    path = Path(path)
    data = yaml.safe_load(path.read_text()) or {}
    if key not in data:
        raise ValueError(f'{path} has no top-level key {key!r}')
    section = data[key] or {}
    section = section.get('ros__parameters', section)
    names = {f.name for f in dataclasses.fields(cls)}
    return make_config(cls, {k: v for k, v in section.items() if k in names})
