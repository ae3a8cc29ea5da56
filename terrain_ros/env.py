"""Safe environment defaults for every entry point of the project.

* ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless the user set it: DDS discovery does not
  multicast out of the network interface. To span several computers, export
  ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` (and the network profile below) yourself.
* ``FASTRTPS_DEFAULT_PROFILES_FILE`` -> ``config/fastdds.xml`` unless set: a 32 MiB shared-memory
  segment so 640x480 point clouds are not silently dropped, UDP on loopback only.
* ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp`` unless set (the only RMW the venv installs).

:func:`node_env` adds, for the node processes a launcher starts, one worker thread per
OpenMP/BLAS/OpenCV pool (``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``,
``OPENCV_FOR_THREADS_NUM`` = 1 unless set): the graph is already parallel across processes, and
a pool's spinning workers take the cores from the other nodes and the simulator. ``terrain-bench
pipeline`` measures it on a recorded run: with one thread per OpenMP/BLAS pool the ICP mapper's
update took 1.81x less CPU and a capture's whole pipeline 1.28x less on a quiet machine (1.15x
and 1.05x with the closed-loop benchmark running beside it; docs/BENCHMARKS.md). OpenCV's pool
(StereoBM, the patches' bilateral filter) splits a call over both cores, so in the loop a half
waits whenever the simulator holds the other core: with one thread the stereo node's run-queue
wait fell from 33.8 to 10.8 s over a rocks-6cm trial (seed 147, 17.1 -> 13.9 s of CPU) and its
stage from 53.2 to 47.0 ms (docs/CLOSED_LOOP.md, thirty-ninth session). Export a larger value
to give a node more threads on a bigger computer.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import List, MutableMapping, Optional

CONFIG_DIR = Path(__file__).resolve().parent.parent / 'config'


def config_path(name: str) -> Path:
    """Path of a file in the project's ``config/`` folder."""
    return CONFIG_DIR / name


def params_files(name: str, robot: str) -> List[Path]:
    """``config/NAME`` and after it, if present, the robot's overlay ``config/STEM.ROBOT.yaml``:
    what the launch profiles load (``params: [NAME, "STEM.${robot}.yaml?"]``), later files
    overriding earlier ones."""
    base = config_path(name)
    overlay = base.with_name(f'{base.stem}.{robot}{base.suffix}')
    return [base, overlay] if overlay.is_file() else [base]


def safe_env(env: Optional[MutableMapping[str, str]] = None) -> MutableMapping[str, str]:
    """Fill in the defaults in ``env`` (default: ``os.environ``) without overriding user values."""
    env = os.environ if env is None else env
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    profile = config_path('fastdds.xml')
    if profile.is_file():
        env.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(profile))
    return env


#: Thread-pool sizes :func:`node_env` sets unless the user did.
NODE_THREAD_DEFAULTS = {'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1',
                        'MKL_NUM_THREADS': '1', 'OPENCV_FOR_THREADS_NUM': '1'}


def node_env(env: Optional[MutableMapping[str, str]] = None) -> MutableMapping[str, str]:
    """:func:`safe_env` plus one thread per OpenMP/BLAS pool (see the module docstring)."""
    env = safe_env(env)
    for k, v in NODE_THREAD_DEFAULTS.items():
        env.setdefault(k, v)
    return env


def apply_safe_defaults() -> None:
    """Apply :func:`safe_env` to this process's environment."""
    safe_env(os.environ)
