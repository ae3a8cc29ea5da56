"""Optional compiled (numba) kernels: one loader for every module that has them.

Each kernel module (``_ik_kernel``, ``_mapping_kernels``, ``_patch_kernels``,
``_body_path_kernel``) repeats a numpy reference in compiled form; an environment variable set
to 0/false/no/off selects the numpy code, and so does a missing numba (logged once, at import).
"""

from __future__ import annotations

import importlib
import logging
import os
from types import ModuleType
from typing import Optional


def load_compiled(module: str, env_var: str, what: str, log: logging.Logger,
                  fallback: str = 'using the numpy code') -> Optional[ModuleType]:
    """``terrain_perception.<module>``, or None for the numpy code: when ``env_var`` is
    0/false/no/off, or when importing it fails (numba missing; ``log`` warns, naming ``what``
    and the ``fallback``)."""
    if os.environ.get(env_var, '1').strip().lower() in ('0', 'false', 'no', 'off'):
        return None
    try:
        return importlib.import_module(f'terrain_perception.{module}')
    except ImportError as e:
        log.warning('%s: numba is not available (%s); %s', what, e, fallback)
        return None


__all__ = ['load_compiled']
