"""Shared pieces of the CLI tools: message types by name, QoS matching, message printing."""

from __future__ import annotations

import importlib
import os
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy


class ToolError(Exception):
    """A user-facing failure: printed as one line, exit code 1."""


def fail(prog: str, exc: BaseException) -> int:
    """Print ``exc`` as one error line (library messages can span several) and return 1."""
    text = ' '.join(str(exc).split())
    print(f'{prog}: error: {text}', file=sys.stderr)
    return 1


def split_type(type_name: str) -> Tuple[str, str, str]:
    """'pkg/msg/Name' (or 'pkg/Name') -> (pkg, 'msg', Name)."""
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ToolError(f'malformed message type {type_name!r} (expected pkg/msg/Name)')
    return parts[0], parts[1], parts[2]


def message_class(type_name: str):
    """The rclpy message class for 'pkg/msg/Name'; ToolError if it is not installed."""
    pkg, kind, name = split_type(type_name)
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError):
        raise ToolError(f'unknown message type {type_name!r}: no Python package provides it '
                        f'(is {pkg} installed in this environment?)') from None


def _prefixes() -> List[Path]:
    out = [Path(sys.prefix)]
    for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if p:
            out.append(Path(p))
    return out


def msg_definition_file(type_name: str) -> Optional[Path]:
    """The installed .msg text of a type (share/<pkg>/msg/<Name>.msg), if any."""
    pkg, kind, name = split_type(type_name)
    for prefix in _prefixes():
        f = prefix / 'share' / pkg / kind / f'{name}.msg'
        if f.is_file():
            return f
    return None


def typestore_with(type_names: List[str]):
    """A rosbags Jazzy typestore that also knows ``type_names`` (read from installed .msg files)."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    store = get_typestore(Stores.ROS2_JAZZY)

    def register(t: str) -> None:
        if t in store.fielddefs:
            return
        f = msg_definition_file(t)
        if f is None:
            raise ToolError(f'no message definition found for {t!r} '
                            f'(looked for share/{"/".join(split_type(t))}.msg)')
        types = get_types_from_msg(f.read_text(), t)
        for _, fielddef in types[t][1]:
            for dep in _referenced_types(fielddef):
                register(dep)  # dependencies first: register() checks them
        store.register(types)

    for t in type_names:
        register(t)
    return store


def _referenced_types(fielddef) -> List[str]:
    # rosbags fielddef: (Nodetype, payload); NAME = 2, SEQUENCE/ARRAY wrap (Nodetype, payload).
    kind, payload = fielddef
    if getattr(kind, 'name', '') == 'NAME':
        return [payload]
    if getattr(kind, 'name', '') in ('ARRAY', 'SEQUENCE'):
        return _referenced_types(payload[0])
    return []


def wait_for_topic(node: Node, topic: str, timeout_s: float,
                   need_publisher: bool = True) -> str:
    """Wait for discovery until ``topic`` has a (publisher) endpoint; return its type name.

    The graph cache fills in the background, so this only polls (no executor needed)."""
    deadline = time.monotonic() + timeout_s
    while True:
        types = dict(node.get_topic_names_and_types())
        if topic in types and (not need_publisher or node.count_publishers(topic) > 0):
            return types[topic][0]
        if time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    if topic in dict(node.get_topic_names_and_types()):
        raise ToolError(f'topic {topic!r} has no publisher (waited {timeout_s:.1f} s)')
    raise ToolError(f'topic {topic!r} does not exist (nothing published or subscribed it '
                    f'within {timeout_s:.1f} s)')


def qos_matching_publishers(node: Node, topic: str, depth: int = 100) -> QoSProfile:
    """A subscription QoS that receives from every current publisher of ``topic``.

    Reliable only if all publishers are reliable; transient local only if all are (then latched
    messages are received too) — the rule ``ros2 topic echo`` uses.
    """
    infos = node.get_publishers_info_by_topic(topic)
    qos = QoSProfile(depth=depth)
    if infos and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos):
        qos.reliability = ReliabilityPolicy.RELIABLE
    else:
        qos.reliability = ReliabilityPolicy.BEST_EFFORT
    if infos and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                     for i in infos):
        qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
    else:
        qos.durability = DurabilityPolicy.VOLATILE
    return qos


def msg_to_plain(msg: Any, max_array: int = 16) -> Any:
    """A message as nested dicts/lists (arrays longer than ``max_array`` summarised)."""
    if hasattr(msg, 'get_fields_and_field_types'):
        return {f: msg_to_plain(getattr(msg, f), max_array)
                for f in msg.get_fields_and_field_types()}
    if isinstance(msg, (bytes, bytearray)) or type(msg).__name__ == 'ndarray' \
            or isinstance(msg, (list, tuple)) or type(msg).__name__ == 'array':
        seq = list(msg)
        if max_array and len(seq) > max_array:
            head = [msg_to_plain(v, max_array) for v in seq[:max_array]]
            return head + [f'... ({len(seq)} items)']
        return [msg_to_plain(v, max_array) for v in seq]
    if hasattr(msg, 'item'):
        return msg.item()
    return msg


def to_yaml(plain: Any, indent: int = 0) -> str:
    """Minimal YAML rendering of :func:`msg_to_plain` output (like ``ros2 topic echo``)."""
    pad = '  ' * indent
    if isinstance(plain, dict):
        lines = []
        for k, v in plain.items():
            if isinstance(v, (dict, list)) and v:
                lines.append(f'{pad}{k}:')
                lines.append(to_yaml(v, indent + 1))
            else:
                lines.append(f'{pad}{k}: {_scalar(v)}')
        return '\n'.join(lines)
    if isinstance(plain, list):
        lines = []
        for v in plain:
            if isinstance(v, dict) and v:
                body = to_yaml(v, indent + 1).lstrip()
                lines.append(f'{pad}- {body}')
            else:
                lines.append(f'{pad}- {_scalar(v)}')
        return '\n'.join(lines)
    return f'{pad}{_scalar(plain)}'


def _scalar(v: Any) -> str:
    if isinstance(v, str):
        return repr(v) if (v == '' or ':' in v or v.strip() != v) else v
    if isinstance(v, (dict, list)):
        return '{}' if isinstance(v, dict) else '[]'
    return str(v)
