"""Config files given with ``--config``: YAML overrides of the defaults, or a saved ``config.yaml``.

A run's or a comparison's own ``config.yaml`` is accepted back as it was written, so a result can
be reproduced from its directory: ``fgslam compare`` writes ``{config: <CompareConfig>,
dead_reckoning: <its resolved config>, inputs: [...]}``, ``fgslam run`` writes the runner, relocalizer and back-end sections beside what it ran
(``backend``, ``relocalization``, ``inputs``), and ``fgslam sim`` writes ``world.yaml`` (its
``config`` section is the simulator's). What describes the inputs is provenance, not config, and
is not read back. Every value is checked by :func:`reloc.config.config_from_dict`; errors name
the file and the key.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ekf.errors import EkfError
from fgslam.errors import FgslamError, InputFileError
from reloc.errors import ConfigError, RelocError

log = logging.getLogger(__name__)

RUN_RECORD_KEYS = ("backend", "relocalization", "inputs")  # what `fgslam run` saves beside its config
SIM_RECORD_KEYS = ("world", "seed", "source", "extent", "orbital_extent", "orbital_gsd_m", "relief_m", "preset", "stats",
                   "bag",  # how the bag was written (sim.bag_scene.bag_description)
                   # a kilometre preset's world.yaml (sim.tiled.outputs) also records these
                   "summary", "orbital_image", "rock_model", "crater_model", "route", "backend_overrides", "relocalizer", "dem")


def read_yaml_mapping(path: Path, what: str = "config") -> dict:
    """The mapping in YAML file ``path`` ({} for an empty file); InputFileError naming the file otherwise."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: {what} file not found" if not path.exists() else f"{path}: not a file")
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: not valid YAML: {exc}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputFileError(f"{path}: the {what} must be a mapping of keys to values, got {type(data).__name__}")
    return data


def compare_overrides(data: dict) -> dict:
    """CompareConfig overrides from a file's mapping: plain overrides, or a saved run/compare config."""
    if "config" in data and set(data) <= {"config", "inputs", "dead_reckoning"}:  # a comparison's config.yaml
        return data["config"] if data["config"] is not None else {}
    if "backend_config" in data or "backend" in data:  # a run's config.yaml
        backend = data.get("backend")
        if not isinstance(backend, str):
            raise ConfigError(f"backend: a saved run's config names its back-end, got {backend!r}")
        rest = {k: v for k, v in data.items() if k not in (*RUN_RECORD_KEYS, "backend_config")}
        overrides = dict(rest.pop("backend_overrides", None) or {})
        if data.get("backend_config"):
            overrides[backend] = data["backend_config"]
        return {**rest, "backend_overrides": overrides} if overrides else rest
    return data


def load_compare_config(path: Path | None):
    """:class:`fgslam.compare.CompareConfig` from ``path`` (the defaults when None)."""
    from fgslam.compare import CompareConfig
    from reloc.config import config_from_dict

    if path is None:
        return CompareConfig()
    data = read_yaml_mapping(path)
    try:
        return config_from_dict(CompareConfig, compare_overrides(data))
    except (FgslamError, RelocError, EkfError) as exc:  # ConfigError or a stage config's own error
        raise ConfigError(f"{path}: {exc}") from None


def sim_overrides(data: dict) -> dict:
    """SimConfig overrides from a file's mapping: plain overrides, or a saved ``world.yaml``."""
    if isinstance(data.get("config"), dict) and set(data) <= {"config", *SIM_RECORD_KEYS}:
        return data["config"]
    return data
