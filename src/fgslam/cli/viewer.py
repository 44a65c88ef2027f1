"""Live rerun viewing for the commands that record (``run``, ``compare``, ``demo``):
``--spawn`` (a native viewer), ``--serve PORT`` (a gRPC server only, for viewers that connect
later), both started on 127.0.0.1, or ``--connect URL`` (a viewer or server already running)."""

from __future__ import annotations

import typer

SPAWN_PORT = 9876  # rerun's own default

SPAWN_HELP = "Open a rerun viewer (started on 127.0.0.1:9876) and stream the recording to it."
SERVE_HELP = "Start a rerun gRPC server on 127.0.0.1:PORT that keeps the recording for viewers (rerun --connect rerun+http://127.0.0.1:PORT/proxy)."
CONNECT_HELP = "Stream the recording to a running rerun viewer or server, e.g. rerun+http://127.0.0.1:9876/proxy."


def live_url(spawn: bool, serve: int | None, connect: str | None, console) -> str | None:
    """The gRPC URL to stream to (None: no live viewing), the viewer or server started first."""
    from fgslam.viz.rerun_log import start_viewer, viewer_url

    chosen = [name for name, on in (("--spawn", spawn), ("--serve", serve is not None), ("--connect", connect)) if on]
    if len(chosen) > 1:
        raise typer.BadParameter(f"{' and '.join(chosen)} exclude each other")
    if connect:
        if not connect.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise typer.BadParameter(f"--connect takes a rerun gRPC URL (rerun+http://HOST:PORT/proxy), got {connect!r}")
        return connect
    if spawn or serve is not None:
        port = SPAWN_PORT if spawn else serve
        if not 0 < port < 65536:
            raise typer.BadParameter(f"--serve takes a port 1-65535, got {port}")
        proc = start_viewer(port, serve_only=not spawn)
        url = viewer_url(port)
        console.print(f"rerun {'viewer' if spawn else 'server'} (pid {proc.pid}) on {url}"
                      + ("" if spawn else f"; view with: rerun --connect {url}; stop it with: kill -- -{proc.pid}"))
        # (its process group: `rerun` is a Python launcher whose child is the server binary, and
        # a plain kill of the launcher leaves the server running)
        return url
    return None
