"""EKF test fixtures.

- The linear algebra runs on one BLAS thread (the filter is sized for one core, and a
  multi-threaded BLAS on a loaded machine is many times slower, not faster).
- ``ekf_synth`` (the small synthetic world) is registered as a module so that the test modules
  can import it under any pytest import mode.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

try:
    from threadpoolctl import threadpool_limits
except ImportError:  # optional: only changes speed, never results
    threadpool_limits = None

if "ekf_synth" not in sys.modules:
    _spec = importlib.util.spec_from_file_location("ekf_synth", Path(__file__).with_name("ekf_synth.py"))
    _mod = importlib.util.module_from_spec(_spec)
    sys.modules["ekf_synth"] = _mod
    _spec.loader.exec_module(_mod)


@pytest.fixture(autouse=True, scope="session")
def _one_blas_thread():
    if threadpool_limits is None:
        yield
        return
    with threadpool_limits(limits=1):
        yield
