"""``python -m fgslam.bench.consistency DIR``: how a back-end's error and its own covariance grow
together over a ``fgslam sim`` directory's stream, without fixes.

SLAM without fixes cannot observe the world's position and heading, so an honest back-end's
covariance grows with the error; one that stays small while the error grows is what later keeps
fixes from pulling (docs/ekf.md, "Consistency"). The back-end runs with the settings ``fgslam
run DIR`` gives it (:class:`fgslam.run_setup.RunSetup`: the directory's ``backend.yaml``, the
long-traverse settings; rocks only unless ``--craters``), over the first ``--duration-s``
seconds, and every ``--bin-s`` seconds of stream the table gives the distance driven, the RMS
planar error and the mean planar sigma, the height error and sigma and the yaw error and sigma at
the bin's end, and the mean position and yaw NEES of the bin.
The whole stretch's NEES gets the two-sided verdict of :func:`fgslam.nees.whitened_test`.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np


def _set(over: dict, assignment: str) -> None:
    """``a.b=value`` (value as YAML, :func:`fgslam.campaign.spec.parse_value`) into the nested
    overrides ``over``."""
    from fgslam.campaign.spec import CampaignError, parse_value, split_assignment

    try:
        key, text = split_assignment(assignment)
        value = parse_value(text)
    except CampaignError as exc:
        raise SystemExit(f"--set {assignment!r}: expected KEY=VALUE (KEY dotted, VALUE as YAML): {exc}") from None
    *path, last = key.split(".")
    node = over
    for k in path:
        node = node.setdefault(k, {})
        if not isinstance(node, dict):
            raise SystemExit(f"--set {assignment!r}: {k} is not a block")
    node[last] = value


def drift_table(directory: Path, backend: str, duration_s: float, bin_s: float = 250.0,
                craters: bool = False, sets: tuple[str, ...] = ()) -> dict:
    """The back-end over the first ``duration_s`` s of ``directory`` (see module doc): JSON-ready."""
    from fgslam import metrics as M
    from fgslam.run_setup import RunSetup

    setup = RunSetup.of_directory(directory, None, duration_s)
    gt = setup.gt
    if gt is None or not len(gt):
        raise SystemExit(f"{directory}: no ground truth in the bag")
    extra: dict = {} if craters else {"kinds": {"craters": {"use": False}}}
    for a in sets:
        _set(extra, a)
    be = setup.backend(backend, extra)
    t0 = time.perf_counter()
    res = setup.run(be)
    wall = time.perf_counter() - t0
    cons, ser = M.consistency(res.online, gt)
    t = ser["t"] - ser["t"][0]
    p_gt, _, _ = M.interpolate_truth(gt, ser["t"])
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p_gt[:, :2], axis=0), axis=1))])
    rows = []
    for lo in np.arange(0.0, t[-1], bin_s):
        m = (t >= lo) & (t < lo + bin_s)
        if not m.any():
            continue
        i = np.flatnonzero(m)[-1]
        rows.append({
            "t_s": round(float(lo + bin_s), 1), "distance_m": round(float(dist[i]), 1),
            "err_xy_m": round(float(np.sqrt(np.mean(np.sum(ser["err_xy"][m] ** 2, axis=1)))), 3),
            "sigma_xy_m": round(float(np.mean(np.linalg.norm(ser["sigma_xy"][m], axis=1))), 3),
            "err_z_m": round(float(ser["err_z"][i]), 3),
            "sigma_z_m": round(float(ser["sigma_z"][i]), 3),
            "err_yaw_deg": round(float(np.degrees(ser["err_yaw"][i])), 3),
            "sigma_yaw_deg": round(float(np.degrees(ser["sigma_yaw"][i])), 3),
            "nees_xy": round(float(np.mean(ser["nees_xy"][m])), 2),
            "nees_yaw": round(float(np.mean(ser["nees_yaw"][m])), 2),
        })
    return {"directory": str(directory), "backend": backend, "duration_s": duration_s, "craters": craters,
            "overrides": setup.overrides(backend, extra), "ate_m": M.ate(res.final, gt).rmse, "wall_s": round(wall, 1),
            "consistency": cons.to_dict(), "bins": rows, "calibration": res.stats.extra.get("calibration")}


def format_table(res: dict) -> str:
    c = res["consistency"]
    head = (f"{res['backend']} over the first {res['duration_s']:g} s of {res['directory']} (no fixes): "
            f"ATE {res['ate_m']:.3f} m, position NEES {c['position']['mean']:.2f} ({c['position']['verdict']}), "
            f"yaw NEES {c['yaw']['mean']:.2f} ({c['yaw']['verdict']}), {res['wall_s']:.0f} s wall")
    lines = [head, "", "| t s | distance m | error xy m | sigma xy m | height error m | height sigma m "
             "| yaw error deg | yaw sigma deg | NEES xy | NEES yaw |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["bins"]:
        lines.append(f"| {r['t_s']:g} | {r['distance_m']:.1f} | {r['err_xy_m']:.3f} | {r['sigma_xy_m']:.3f} | "
                     f"{r['err_z_m']:+.3f} | {r['sigma_z_m']:.3f} | {r['err_yaw_deg']:+.3f} | "
                     f"{r['sigma_yaw_deg']:.3f} | {r['nees_xy']:.2f} | {r['nees_yaw']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("directory", type=Path)
    ap.add_argument("--backend", default="ekf", choices=("ekf", "isam2"))
    ap.add_argument("--duration-s", type=float, default=3000.0)
    ap.add_argument("--bin-s", type=float, default=250.0)
    ap.add_argument("--craters", action="store_true", help="map craters too (rocks only by default)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="a back-end override, dotted (e.g. first_estimate_jacobians=false); repeatable")
    ap.add_argument("--out", type=Path, help="write the results as JSON here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if not args.duration_s > 0 or not args.bin_s > 0:
        raise SystemExit("--duration-s and --bin-s must be positive")
    res = drift_table(args.directory, args.backend, args.duration_s, args.bin_s, args.craters, tuple(args.sets))
    if args.out is not None:
        args.out.write_text(json.dumps(res, indent=1, default=str))
    print(format_table(res))
    return res


if __name__ == "__main__":
    main()
