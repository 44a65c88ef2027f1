"""``fgslam config dump``: the complete configuration (every default) as YAML, reusable with ``--config``."""

from __future__ import annotations

from pathlib import Path

import typer

from fgslam.cli.app import config_app


def dump_text(what: str, config: Path | None = None) -> str:
    """YAML of the complete ``run`` (runner, relocalizer, every back-end's resolved config, topics,
    images, ...: what ``fgslam run`` / ``compare`` take) or ``sim`` config, ``config``'s overrides applied."""
    import yaml

    from fgslam.report import _jsonable

    if what == "run":
        from fgslam.backends.registry import BACKEND_NAMES, resolved_config
        from fgslam.cli.cmd_run import load_config
        from fgslam.compare import resolved_compare_config

        cfg = load_config(config)
        data = resolved_compare_config(cfg)
        data["backend_overrides"] = {name: resolved_config(name, cfg.backend_overrides.get(name))
                                     for name in BACKEND_NAMES}  # every back-end, not only the compared ones
    elif what == "sim":
        from fgslam.cli.cmd_sim import load_sim_config
        from reloc.config import config_to_dict

        data = config_to_dict(load_sim_config(None, None, None, config))
    else:
        raise typer.BadParameter(f"config dump takes run or sim, got {what!r}")
    return yaml.safe_dump(_jsonable(data), sort_keys=False)


@config_app.command("dump")
def dump_cmd(
    what: str = typer.Argument("run", help="run (for fgslam run / compare / demo) or sim (for fgslam sim)."),
    config: Path | None = typer.Option(None, "--config", help="Apply these overrides first."),
    out: Path | None = typer.Option(None, "--out", help="Write to this file instead of standard output."),
) -> None:
    """Print the complete configuration, every default resolved; give it back with --config."""
    text = dump_text(what, config)
    if out is None:
        typer.echo(text, nl=False)
        return
    from fgslam.io.outdir import atomic_path, check_output_path

    check_output_path(out, "--out", directory=False)
    with atomic_path(out, "--out") as tmp:
        Path(tmp).write_text(text)
    typer.echo(f"wrote {out}", err=True)
