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


@pytest.mark.parametrize("name", ["relocalization.ipynb", "compare_ekf_isam2.ipynb"])
def test_rendered_page_shows_the_notebooks_current_code_and_figures(name):
    """docs/notebooks/<name>.md (notebooks/render.py) holds every code cell of the notebook as it
    is now, in order, and its figures exist: re-render after editing a notebook."""
    import re

    import nbformat

    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    page = NOTEBOOKS.parent / "docs" / "notebooks" / f"{Path(name).stem}.md"
    assert page.is_file(), f"{page} is missing: run notebooks/render.py"
    text = page.read_text()
    code = [c.source for c in nb.cells if c.cell_type == "code"]
    shown = re.findall(r"```python\n(.*?)\n```\n", text, flags=re.S)
    assert shown == code, f"{page} is stale: run notebooks/render.py"
    images = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", text)
    assert images, f"{page} shows no figure"
    for img in images:
        assert (page.parent / img).is_file(), img
