"""Render the notebooks into docs/notebooks/ so a reader sees their figures without running them.

    .venv/bin/python notebooks/render.py            # executes each notebook (nbclient), writes
                                                    # docs/notebooks/<name>.md and <name>_files/*.png

Markdown cells are copied, code cells become ```python blocks, text outputs ``` blocks and images
PNG files beside the page. The notebooks themselves stay without outputs; the test suite executes
them (tests/notebooks) and checks that each page shows its notebook's current code.
"""

from __future__ import annotations

import base64
import logging
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
DOCS = HERE.parent / "docs" / "notebooks"
NOTEBOOKS = ("compare_ekf_isam2.ipynb", "relocalization.ipynb")

log = logging.getLogger("render")
OPEN3D_NOTICES = ("Jupyter environment detected", "[Open3D INFO]")  # printed by its import in a kernel


def to_markdown(nb, name: str, files_dir: Path) -> str:
    """Markdown of the executed notebook ``nb``; its images written into ``files_dir``."""
    parts = [f"<!-- rendered from notebooks/{name}.ipynb by notebooks/render.py; do not edit -->\n"]
    files_dir.mkdir(parents=True, exist_ok=True)
    for k, cell in enumerate(nb.cells):
        if cell.cell_type == "markdown":
            parts.append(cell.source + "\n")
            continue
        if cell.cell_type != "code":
            continue
        parts.append(f"```python\n{cell.source}\n```\n")
        for j, out in enumerate(cell.get("outputs", [])):
            data = out.get("data", {})
            if "image/png" in data:
                png = files_dir / f"cell{k:02d}_{j}.png"
                png.write_bytes(base64.b64decode(data["image/png"]))
                parts.append(f"![output of cell {k}]({files_dir.name}/{png.name})\n")
            elif out.get("output_type") == "stream" and out.get("name") == "stdout":
                lines = [ln for ln in out["text"].splitlines() if not ln.startswith(OPEN3D_NOTICES)]
                if lines:
                    parts.append("```text\n" + "\n".join(lines).rstrip() + "\n```\n")
            elif "text/markdown" in data:
                parts.append(data["text/markdown"].rstrip() + "\n")
            elif "text/plain" in data:
                parts.append(f"```text\n{data['text/plain'].rstrip()}\n```\n")
    return "\n".join(parts)


def render(name: str) -> Path:
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(HERE / name, as_version=4)
    with tempfile.TemporaryDirectory() as tmp:  # the notebooks' own files go there, not into notebooks/
        NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": tmp}}).execute()
    stem = Path(name).stem
    files_dir = DOCS / f"{stem}_files"
    shutil.rmtree(files_dir, ignore_errors=True)
    page = DOCS / f"{stem}.md"
    page.write_text(to_markdown(nb, stem, files_dir))
    return page


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for n in sys.argv[1:] or NOTEBOOKS:
        log.info("rendered %s", render(n))
