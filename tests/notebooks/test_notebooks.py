"""Execute the notebooks (nbmake, the venv's python3 kernel) on their small seeded runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["relocalization.ipynb", "compare_ekf_isam2.ipynb"])
def test_notebook_executes(name, tmp_path):
    nb = NOTEBOOKS / name
    assert nb.exists(), f"{nb} is missing"
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "--nbmake", "--nbmake-timeout=300", "-q", "-p", "no:cacheprovider",
         "--rootdir", str(tmp_path), str(nb)],
        check=False, capture_output=True, text=True, cwd=tmp_path,
    )
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
