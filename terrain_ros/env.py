"""Safe environment defaults for every entry point of the project.

* ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless the user set it: DDS discovery does not
  multicast out of the network interface. To span several computers, export
  ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` (and the network profile below) yourself.
* ``FASTRTPS_DEFAULT_PROFILES_FILE`` -> ``config/fastdds.xml`` unless set: a 32 MiB shared-memory
  segment so 640x480 point clouds are not silently dropped, UDP on loopback only.
* ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp`` unless set (the only RMW the venv installs).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import MutableMapping, Optional

CONFIG_DIR = Path(__file__).resolve().parent.parent / 'config'


def config_path(name: str) -> Path:
    """Path of a file in the project's ``config/`` folder."""
    return CONFIG_DIR / name


def safe_env(env: Optional[MutableMapping[str, str]] = None) -> MutableMapping[str, str]:
    """Fill in the defaults in ``env`` (default: ``os.environ``) without overriding user values."""
    env = os.environ if env is None else env
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    profile = config_path('fastdds.xml')
    if profile.is_file():
        env.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(profile))
    return env


def apply_safe_defaults() -> None:
    """Apply :func:`safe_env` to this process's environment."""
    safe_env(os.environ)
