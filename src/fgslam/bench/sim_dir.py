"""The command line of the monitors' replays over an ``fgslam sim`` directory (``python -m
fgslam.bench.slip DIR``, ``python -m fgslam.bench.gyro DIR``); a run over one as ``fgslam run``
makes it is :class:`fgslam.run_setup.RunSetup`."""

from __future__ import annotations

from pathlib import Path


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
