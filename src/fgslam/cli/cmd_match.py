"""``fgslam match``: locate a local rock map (CSV) in a rock catalog (CSV)."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import app


@app.command("match")
def match_cmd(
    catalog: Path = typer.Option(..., "--catalog", help="Catalog CSV (x,y,size[,score]; metres, world frame)."),
    local: Path = typer.Option(..., "--local", help="Local map CSV, same columns, in the local frame."),
    json_out: bool = typer.Option(False, "--json", help="Print the result as one JSON object."),
    seed: int = typer.Option(0, "--seed", help="Seed of the order in which local triangles are tried."),
    sigma: float = typer.Option(0.1, "--sigma", help="Expected position noise between the maps (m, per axis)."),
) -> None:
    """Find the transform world = scale * R(theta) @ local + t, or report that there is no match (exit 1)."""
    import json
    import math

    import numpy as np

    from fgslam.io.catalog_csv import read_catalog_csv
    from reloc import Catalog, ConstellationMatcher, MatcherConfig

    cat_csv = read_catalog_csv(catalog)
    loc_csv = read_catalog_csv(local)
    cat = Catalog(cat_csv.xy_m, cat_csv.size_m)
    matcher = ConstellationMatcher(cat, MatcherConfig(sigma_m=sigma, seed=seed))
    result = matcher.match(loc_csv.xy_m, loc_csv.size_m)
    if result is None:
        if json_out:
            typer.echo(json.dumps({"match": False, "n_local": len(loc_csv), "n_catalog": len(cat)}))
        else:
            typer.echo(f"no match: {len(loc_csv)} local rocks against {len(cat)} catalog rocks")
        raise typer.Exit(1)
    payload = {
        "match": True,
        "rotation_rad": result.rotation_rad,
        "rotation_deg": math.degrees(result.rotation_rad),
        "translation": [float(v) for v in result.translation],
        "scale": result.scale,
        "n_inliers": result.n_inliers,
        "rmse_m": result.rmse_m,
        "log10_false_alarm": result.log10_false_alarm,
        "n_hypotheses": result.n_hypotheses,
        "transform_cov": np.asarray(result.transform_cov).tolist(),
        "inlier_pairs": np.asarray(result.inlier_pairs).tolist(),
    }
    if json_out:
        typer.echo(json.dumps(payload))
        return
    typer.echo(
        f"match: theta {payload['rotation_deg']:.3f} deg, t ({result.translation[0]:.3f}, "
        f"{result.translation[1]:.3f}) m, scale {result.scale:.4f}, {result.n_inliers} inliers, "
        f"RMSE {result.rmse_m:.3f} m, log10 false alarm {result.log10_false_alarm:.1f}"
    )
