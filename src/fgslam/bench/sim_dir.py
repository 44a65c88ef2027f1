"""What the benchmarks share about an ``fgslam sim`` directory: the back-end overrides its
``backend.yaml`` gives, the first seconds of its stream, and the command line of the monitors'
replays over it (``python -m fgslam.bench.slip DIR``, ``python -m fgslam.bench.gyro DIR``)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path


def directory_overrides(directory: Path, backend: str, craters_used: bool) -> dict:
    """The ``backend_overrides`` of ``backend`` in ``directory/backend.yaml`` (empty without the
    file); with ``craters_used`` false, crater frames are counted and left out (``kinds.craters.use``)."""
    from fgslam.config_file import read_yaml_mapping

    f = Path(directory) / "backend.yaml"
    data = read_yaml_mapping(f) if f.exists() else {}
    over = dict((data.get("backend_overrides") or {}).get(backend) or {})
    if not craters_used:
        kinds = dict(over.get("kinds", {}))
        kinds["craters"] = {**dict(kinds.get("craters", {})), "use": False}
        over["kinds"] = kinds
    return over


def first_seconds(measurements: Iterable, duration_s: float | None) -> Iterator:
    """The measurements of the first ``duration_s`` seconds (all of them for None), lazily."""
    if duration_s is None:
        yield from measurements
        return
    t_end = None
    for m in measurements:
        if t_end is None:
            t_end = m.t + duration_s
        if m.t > t_end:
            return
        yield m


def replay_main(description: str, replay, argv: list[str] | None = None) -> dict:
    """``DIR [--out FILE]``: ``replay(DIR)``, printed and written as JSON."""
    import argparse
    import json
    import logging

    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("directory", type=Path)
    ap.add_argument("--out", type=Path, help="write the results as JSON here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    res = replay(args.directory)
    text = json.dumps(res, indent=1)
    if args.out is not None:
        args.out.write_text(text)
    print(text)
    return res
