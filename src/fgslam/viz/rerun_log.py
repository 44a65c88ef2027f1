"""The one rerun module: entity paths, the timeline, the blueprint, and .rrd writers.

Everything is drawn as a flat map in 3D views (x/y world metres, z = a layer height), so the
orbital image can be a textured quad under the catalog, the truth and the estimates. Per world
``W`` and variant key ``K`` ("ekf", "ekf_reloc", "isam2", "isam2_reloc"):

- ``/W/map/orbital/X_Y`` (tiles of the orbital image along the path, :mod:`fgslam.viz.orbital_tiles`),
  ``/W/map/catalog/KIND`` (each landmark kind's catalog, on the same ground), ``/W/map/truth`` (static), ``/W/map/truth_pose`` (timeline);
- ``/W/K/path`` (final trajectory, static), ``/W/K/pose``, ``/W/K/heading`` and ``/W/K/pose_cov``
  (online estimate, an arrow along its heading, and its 3-sigma x/y ellipse, timeline), ``/W/K/landmarks/KIND`` (each kind's final map, static:
  3-sigma discs by default),
  ``/W/K/fixes`` (fix events at t_recv, green accepted / red rejected);
- ``/W/matches`` (matched local->catalog rock pairs at t_meas);
- ``/W/errors/position/K`` and ``.../K_3sigma``, ``/W/errors/yaw/K`` and ``.../K_3sigma`` (scalars).

Catalogs and maps are drawn by their kind's rerun layer (:mod:`reloc.kinds`; the default,
:class:`fgslam.viz.landmarks.PointLandmarkLogger`, draws discs and 3-sigma ellipses). Time is
stream seconds on the ``sim_time`` timeline. The error curves are the *online* estimate's (what
the rover knew at that time, the same series as the 3-sigma bound); the metrics' ATE is the final
(smoothed) trajectory's, which for iSAM2 is much smaller: ``/W/errors/position/K_final`` draws
that one too. Each bound is drawn in a lighter shade and thinner than its error.

Recordings go to a file (:func:`write_rrd`) or live to a viewer: one run pose by pose as it
runs (:class:`LiveRun`), or a finished comparison at once (:func:`stream_rrd`); the viewer is one
this process starts on 127.0.0.1 (:func:`start_viewer`: a native viewer, or a gRPC server only
that viewers connect to) or any gRPC URL (``rerun+http://HOST:PORT/proxy``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fgslam import metrics as M
from fgslam.viz.orbital_tiles import map_tiles

TIMELINE = "sim_time"
APP_ID = "fgslam"
# layer heights of the flat map (m)
Z_IMAGE, Z_CATALOG, Z_LANDMARKS, Z_TRUTH, Z_PATH, Z_FIX = 0.0, 0.02, 0.04, 0.06, 0.08, 0.1
# downsampling, so a recording grows linearly with the path (< 5 MB per km): time series one
# sample per RRD_STEP_M of path (and at least every RRD_STEP_S), matched pairs one fix per
# RRD_MATCH_STEP_M; the orbital image and the catalogs as fgslam.viz.orbital_tiles cuts them
RRD_STEP_M, RRD_STEP_S, RRD_MATCH_STEP_M = 1.0, 10.0, 5.0

ENT_ORBITAL = "map/orbital"
ENT_CATALOG = "map/catalog"
ENT_TRUTH = "map/truth"
ENT_TRUTH_POSE = "map/truth_pose"
ENT_MATCHES = "matches"
ENT_PATH, ENT_POSE, ENT_POSE_COV, ENT_LANDMARKS, ENT_FIXES = "path", "pose", "pose_cov", "landmarks", "fixes"
ENT_HEADING = "heading"
HEADING_ARROW_M = 0.6
LOCALHOST = "127.0.0.1"
ENT_ERR_POS, ENT_ERR_YAW = "errors/position", "errors/yaw"

COLORS = {"truth": (44, 160, 44), "dr": (127, 127, 127), "ekf": (31, 119, 180), "isam2": (214, 39, 40),
          "ekf_reloc": (23, 190, 207), "isam2_reloc": (255, 127, 14),
          "catalog": (230, 190, 110), "fix_ok": (40, 220, 80), "fix_bad": (230, 40, 40), "match": (255, 150, 20)}


def _color(key: str) -> tuple[int, int, int]:
    """A run's colour: its own when it has one ("ekf_reloc"), else its back-end's ("ekf")."""
    return COLORS.get(key, COLORS.get(key.split("_")[0], (200, 200, 200)))


def landmark_logger(kind: str):
    """The rerun layer of landmark kind ``kind`` (the point default when it registers none)."""
    from fgslam.viz.landmarks import PointLandmarkLogger
    from reloc.kinds import kind_named

    k = kind_named(kind)
    return (k.layer("rerun") if k.has("rerun") else PointLandmarkLogger)(kind)


def _shown_path(gt, runs: dict) -> np.ndarray | None:
    """The path a recording's map is cut around (:mod:`fgslam.viz.orbital_tiles`): the truth's,
    else every run's final path; None (the whole map) for a live run without truth."""
    if gt is not None and len(gt):
        return gt.positions_m[path_samples(gt.t, gt.positions_m, step_s=np.inf), :2]
    paths = [r.final.positions_m[:, :2] for r in runs.values() if len(r.final)]
    return np.vstack(paths) if paths else None


@dataclass(frozen=True)
class ShownCatalog:
    """The catalog entries a recording shows (what a kind's ``log_catalog`` reads)."""

    xy_m: np.ndarray
    size_m: np.ndarray


def _shown_catalog(cat, view):
    """``cat``'s entries on the ground ``view`` (:class:`MapTiles`) shows; all without a view."""
    if view is None:
        return cat
    keep = view.covers(cat.xy_m)
    return ShownCatalog(np.asarray(cat.xy_m, dtype=float)[keep], np.asarray(cat.size_m, dtype=float)[keep])


def path_samples(t: np.ndarray, xy: np.ndarray, step_m: float = RRD_STEP_M, step_s: float = RRD_STEP_S) -> np.ndarray:
    """Indices (sorted) of samples at least ``step_m`` of path or ``step_s`` apart (first and last kept)."""
    n = len(t)
    if n == 0:
        return np.zeros(0, dtype=int)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(np.asarray(xy)[:, :2], axis=0), axis=1))])
    keep, s_last, t_last = [0], 0.0, float(t[0])
    for i in range(1, n):
        if s[i] - s_last >= step_m or t[i] - t_last >= step_s:
            keep.append(i)
            s_last, t_last = s[i], float(t[i])
    if keep[-1] != n - 1:
        keep.append(n - 1)
    return np.asarray(keep, dtype=int)


def along_path(traj):
    """``traj`` at the poses :func:`path_samples` keeps (a recording that grows with distance)."""
    if not len(traj):
        return traj
    k = path_samples(traj.t, traj.positions_m)
    return type(traj)(traj.t[k], traj.T_world_base[k], None if traj.cov is None else traj.cov[k])


def ellipses(cov_xy: np.ndarray, sigmas: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Half sizes (K, 3) and z-rotation quaternions xyzw (K, 4) of the ``sigmas`` ellipses of (K, 2, 2) covariances."""
    w, v = np.linalg.eigh(0.5 * (cov_xy + np.swapaxes(cov_xy, 1, 2)))
    half = np.zeros((len(w), 3))
    half[:, :2] = sigmas * np.sqrt(np.clip(w, 1e-12, None))
    half[:, 2] = 0.005
    ang = np.arctan2(v[:, 1, 0], v[:, 0, 0])
    q = np.zeros((len(w), 4))
    q[:, 2], q[:, 3] = np.sin(ang / 2), np.cos(ang / 2)
    return half, q


def flat(xy: np.ndarray, z: float) -> np.ndarray:
    xy = np.asarray(xy, float).reshape(-1, 2)
    return np.column_stack([xy, np.full(len(xy), z)])


def log_world(rec, world: str, inputs, gt, runs: dict, attempts: list) -> None:
    """Log one world's map, truth, every run of ``runs`` (key -> RunResult) and the fix attempts."""
    import rerun as rr

    def p(*parts: str) -> str:
        return "/".join((world,) + parts)

    view = None
    if inputs.orbital_image is not None and inputs.orbital_extent is not None:
        view = map_tiles(inputs.orbital_image, inputs.orbital_extent, _shown_path(gt, runs))
        for tile in view.tiles:
            x0, x1, y0, y1 = tile.extent
            rec.log(p(ENT_ORBITAL, f"{x0:.0f}_{y1:.0f}"), rr.Mesh3D(
                vertex_positions=[[x0, y1, Z_IMAGE], [x1, y1, Z_IMAGE], [x1, y0, Z_IMAGE], [x0, y0, Z_IMAGE]],
                triangle_indices=[[0, 1, 2], [0, 2, 3]],
                vertex_normals=[[0, 0, 1]] * 4,
                vertex_texcoords=[[0, 0], [1, 0], [1, 1], [0, 1]],
                albedo_texture=tile.image,
            ), static=True)
    for kind, cat in inputs.catalogs.items():
        landmark_logger(kind).log_catalog(rec, p(ENT_CATALOG, kind), _shown_catalog(cat, view))
    if gt is not None:
        k = path_samples(gt.t, gt.positions_m, step_s=np.inf)
        rec.log(p(ENT_TRUTH), rr.LineStrips3D([flat(gt.positions_m[k, :2], Z_TRUTH)], colors=COLORS["truth"],
                                              radii=0.04), static=True)
        step = max(1, len(gt) // 3000)
        rr.send_columns(p(ENT_TRUTH_POSE), indexes=[rr.TimeColumn(TIMELINE, duration=gt.t[::step])],
                        columns=rr.Points3D.columns(positions=flat(gt.positions_m[::step, :2], Z_TRUTH)),
                        recording=rec)
    for key, run in runs.items():
        _log_styles(rec, world, key)
        _log_run_result(rec, world, key, run, gt)
        if len(run.online):
            _log_online(rec, world, key, along_path(run.online), gt)
        _log_fixes(rec, world, key, run.outcomes)
    _log_matches(rec, world, attempts)


def _log_matches(rec, world: str, attempts: list) -> None:
    """Matched local -> catalog pairs at their ``t_meas``, one fix per ``RRD_MATCH_STEP_M`` of path."""
    import rerun as rr

    last_xy = None
    for a in attempts:
        if a.fix is None or len(a.local_xy) == 0:
            continue
        here = np.array([a.fix.x_m, a.fix.y_m])
        if last_xy is not None and np.hypot(*(here - last_xy)) < RRD_MATCH_STEP_M:
            continue
        last_xy = here
        rec.set_time(TIMELINE, duration=a.t_meas)
        strips = [np.array([[*l, Z_FIX], [*w, Z_FIX]]) for l, w in zip(a.local_xy, a.world_xy)]
        rec.log(f"{world}/{ENT_MATCHES}", rr.LineStrips3D(strips, colors=COLORS["match"], radii=0.02))
    rec.reset_time()


def _log_styles(rec, world: str, key: str) -> None:
    """The static styles of a run's time-varying entities: heading arrows and error series."""
    import rerun as rr

    rec.log(f"{world}/{key}/{ENT_HEADING}", rr.Arrows3D.from_fields(colors=_color(key), radii=0.03), static=True)
    for ent, style in _series_entities(key):
        rec.log(f"{world}/{ent}", rr.SeriesLines(colors=_shade(_color(key), style), widths=SERIES_WIDTH[style],
                                                 names=f"{key} {style}"), static=True)


def _log_run_result(rec, world: str, key: str, run, gt) -> None:
    """What only a finished run has: its final path, its landmark maps, the final trajectory's error."""
    import rerun as rr

    col = _color(key)
    if len(run.final):
        k = path_samples(run.final.t, run.final.positions_m, step_s=np.inf)
        rec.log(f"{world}/{key}/{ENT_PATH}", rr.LineStrips3D([flat(run.final.positions_m[k, :2], Z_PATH)],
                                                            colors=col, radii=0.03), static=True)
    for kind, lmap in run.landmarks.items():
        landmark_logger(kind).log_map(rec, f"{world}/{key}/{ENT_LANDMARKS}/{kind}", lmap, col)
    if gt is not None and len(run.final):
        final_err, final_t = M.position_errors(along_path(run.final), gt)
        rr.send_columns(f"{world}/{ENT_ERR_POS}/{key}_final", indexes=[rr.TimeColumn(TIMELINE, duration=final_t)],
                        columns=rr.Scalars.columns(scalars=np.linalg.norm(final_err, axis=1)), recording=rec)


def _log_online(rec, world: str, key: str, on, gt) -> None:
    """The online estimate ``on`` (a Trajectory with covariance, already sampled): pose, heading
    arrow, 3-sigma ellipse and, with truth, the error and 3-sigma series."""
    import rerun as rr

    idx = rr.TimeColumn(TIMELINE, duration=on.t)
    xyz = flat(on.positions_m[:, :2], Z_PATH)
    rr.send_columns(f"{world}/{key}/{ENT_POSE}", indexes=[idx], columns=rr.Points3D.columns(
        positions=xyz, radii=np.full(len(on), 0.12)), recording=rec)
    forward = on.T_world_base[:, :2, 0]  # base_link x axis in world: the heading
    forward = HEADING_ARROW_M * forward / np.maximum(np.linalg.norm(forward, axis=1, keepdims=True), 1e-12)
    rr.send_columns(f"{world}/{key}/{ENT_HEADING}", indexes=[idx], columns=rr.Arrows3D.columns(
        origins=xyz, vectors=flat(forward, 0.0)), recording=rec)
    half, q = ellipses(on.cov[:, :2, :2])
    rr.send_columns(f"{world}/{key}/{ENT_POSE_COV}", indexes=[idx], columns=rr.Ellipsoids3D.columns(
        centers=xyz, half_sizes=half, quaternions=q), recording=rec)
    if gt is None:
        return
    _, s = M.consistency(on, gt)
    if not len(s["t"]):
        return
    mask = np.isin(on.t, s["t"])
    sig_pos = 3.0 * np.sqrt(np.linalg.eigvalsh(on.cov[mask][:, :2, :2])[:, -1])
    values = (np.linalg.norm(s["err_xy"], axis=1), sig_pos, np.degrees(np.abs(s["err_yaw"])),
              np.degrees(3.0 * s["sigma_yaw"]))
    online_entities = [ent for ent, _ in _series_entities(key) if not ent.endswith("_final")]
    for ent, vals in zip(online_entities, values):
        rr.send_columns(f"{world}/{ent}", indexes=[rr.TimeColumn(TIMELINE, duration=s["t"])],
                        columns=rr.Scalars.columns(scalars=vals), recording=rec)


def _log_fixes(rec, world: str, key: str, outcomes: list) -> None:
    """Fix events at ``t_recv``: green accepted, red rejected."""
    import rerun as rr

    if not outcomes:
        return
    t = np.array([o.fix.t_recv for o in outcomes])
    xy = np.array([[o.fix.x_m, o.fix.y_m] for o in outcomes])
    colors = np.array([COLORS["fix_ok"] if o.accepted else COLORS["fix_bad"] for o in outcomes], dtype=np.uint8)
    rr.send_columns(f"{world}/{key}/{ENT_FIXES}", indexes=[rr.TimeColumn(TIMELINE, duration=t)],
                    columns=rr.Points3D.columns(positions=flat(xy, Z_FIX), colors=colors,
                                                radii=np.full(len(t), 0.2)), recording=rec)


SERIES_WIDTH = {"error": 1.5, "3σ": 0.8, "final": 1.0}


def _series_entities(key: str) -> list[tuple[str, str]]:
    """(entity under the world, style) of a run's error series: online position error and its
    3-sigma bound, online yaw error and its bound, the final trajectory's position error."""
    return [(f"{ENT_ERR_POS}/{key}", "error"), (f"{ENT_ERR_POS}/{key}_3sigma", "3σ"),
            (f"{ENT_ERR_YAW}/{key}", "error"), (f"{ENT_ERR_YAW}/{key}_3sigma", "3σ"),
            (f"{ENT_ERR_POS}/{key}_final", "final")]


def _shade(rgb: tuple[int, int, int], style: str) -> tuple[int, int, int]:
    """A run's colour for a series: the error as is, its 3-sigma bound halfway to white, the final
    trajectory's error halfway to black."""
    target = {"error": None, "3σ": 255, "final": 0}[style]
    return rgb if target is None else tuple(int(round(0.5 * (c + target))) for c in rgb)


def world_view(world: str, keys: list[str], center_xy: np.ndarray, span_m: float):
    """Blueprint of one world: the map views of ``keys`` side by side, error time series below."""
    import rerun.blueprint as rrb

    eye = rrb.EyeControls3D(position=[float(center_xy[0]), float(center_xy[1]) - 0.01, 1.2 * span_m],
                            look_target=[float(center_xy[0]), float(center_xy[1]), 0.0], eye_up=[0.0, 1.0, 0.0])
    from fgslam.compare import run_label

    maps = [
        rrb.Spatial3DView(origin=f"/{world}", name=f"{world}: {run_label(k)}",
                          contents=[f"/{world}/map/**", f"/{world}/{k}/**", f"/{world}/{ENT_MATCHES}/**"],
                          eye_controls=eye, line_grid=False)
        for k in keys
    ]
    # the whole traverse on the x axis (not the viewer's default window around the time cursor)
    whole = rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite())
    series = [
        rrb.TimeSeriesView(origin=f"/{world}/{ent}", name=name,
                           axis_x=rrb.TimeAxis(view_range=whole),
                           time_ranges=rrb.VisibleTimeRange(TIMELINE, range=whole))
        for ent, name in ((ENT_ERR_POS, "position error [m] and 3σ"), (ENT_ERR_YAW, "yaw error [deg] and 3σ"))
    ]
    return rrb.Vertical(rrb.Horizontal(*maps), rrb.Horizontal(*series), row_shares=[3, 2], name=world)


def _view_keys(runs: dict) -> list[str]:
    keys = [k for k in runs if k.endswith("_reloc")]
    return keys or list(runs)


def blueprint(worlds: list[tuple[str, list[str], np.ndarray, float]]):
    """Blueprint of a recording: one tab per world (see :func:`world_view`)."""
    import rerun.blueprint as rrb

    views = [world_view(*w) for w in worlds]
    root = views[0] if len(views) == 1 else rrb.Tabs(*views)
    return rrb.Blueprint(
        root,
        rrb.TimePanel(timeline=TIMELINE, play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


LIVE_START_SPAN_M = 40.0  # the live view's first frame without truth: this much around the start


def _frame(inputs, gt, runs) -> tuple[np.ndarray, float]:
    """Centre (2,) and span (m) of a world's map view: the truth's extent, else the runs' final
    paths', else (a live run without truth) ``LIVE_START_SPAN_M`` around the start pose."""
    if gt is not None:
        p = gt.positions_m[:, :2]
    elif runs:
        p = next(iter(runs.values())).final.positions_m[:, :2]
    else:
        c = np.asarray(inputs.initial.position_m[:2], dtype=float)
        return c, LIVE_START_SPAN_M
    lo, hi = p.min(0) - 3.0, p.max(0) + 3.0
    return 0.5 * (lo + hi), float(max(hi - lo))


def write_rrd(path: Path, items: list[tuple[str, object, object, dict, list]], recording_id: str | None = None) -> Path:
    """Write a recording of ``items`` = [(world, inputs, gt, runs, attempts)] with its blueprint to ``path``."""
    import rerun as rr

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    bp = blueprint([(w, _view_keys(runs), *_frame(inp, gt, runs)) for w, inp, gt, runs, _ in items])
    rec.save(str(path), default_blueprint=bp)
    for world, inputs, gt, runs, attempts in items:
        log_world(rec, world, inputs, gt, runs, attempts)
    rec.flush()
    rec.disconnect()
    return path


def viewer_url(port: int, host: str = LOCALHOST) -> str:
    """The gRPC URL an SDK or a viewer connects to."""
    return f"rerun+http://{host}:{int(port)}/proxy"


def start_viewer(port: int, serve_only: bool = False, timeout_s: float = 20.0):
    """Start ``rerun`` bound to 127.0.0.1:``port`` (a native viewer; ``serve_only``: a gRPC
    server only, which keeps what it receives for viewers that connect later with ``rerun
    --connect URL``), detached from this process; wait until it listens. Returns the Popen."""
    import shutil
    import socket
    import subprocess
    import sys
    import time

    from fgslam.errors import FgslamError

    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if exe is None:
        raise FgslamError("the rerun viewer executable is not installed (pip install rerun-sdk)")
    cmd = [exe, "--bind", LOCALHOST, "--port", str(int(port))] + (["--serve-grpc"] if serve_only else [])
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise FgslamError(f"rerun exited at once (status {proc.returncode}): is port {port} already in use?")
        with socket.socket() as sock:
            if sock.connect_ex((LOCALHOST, int(port))) == 0:
                return proc
        time.sleep(0.1)
    signal_viewer(proc.pid)
    raise FgslamError(f"rerun did not listen on {LOCALHOST}:{port} within {timeout_s:g} s")


def signal_viewer(pid: int, sig: int | None = None) -> None:
    """Send ``sig`` (default SIGTERM) to a viewer started by :func:`start_viewer`, whose ``pid`` is
    that of its own process group: ``rerun`` is a Python launcher whose child is the viewer
    binary, and a signal to the launcher alone leaves the binary running, orphaned. A group that
    has ended already is no error."""
    import os
    import signal

    try:
        os.killpg(pid, signal.SIGTERM if sig is None else sig)
    except ProcessLookupError:
        pass


def stream_rrd(url: str, items: list[tuple[str, object, object, dict, list]], recording_id: str | None = None) -> str:
    """Send the recording of ``items`` (as :func:`write_rrd`) with its blueprint to the viewer or
    server at gRPC ``url``; returns ``url``."""
    import rerun as rr

    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    bp = blueprint([(w, _view_keys(runs), *_frame(inp, gt, runs)) for w, inp, gt, runs, _ in items])
    rec.connect_grpc(url, default_blueprint=bp)
    for world, inputs, gt, runs, attempts in items:
        log_world(rec, world, inputs, gt, runs, attempts)
    rec.flush()
    rec.disconnect()
    return url


LIVE_STEP_S = 1.0  # live: a pose at least every second of stream time (and every RRD_STEP_M of path)


class LiveRun:
    """One run streamed to a viewer or server at gRPC ``url`` *while it runs* (``fgslam run
    --spawn / --serve / --connect``; a :class:`fgslam.runner.RunObserver`). The map, the catalogs
    and the truth go first. Then the online pose, its heading and 3-sigma ellipse, and (with truth)
    the error curves follow as the runner records them: one sample per ``RRD_STEP_M`` of path or
    ``LIVE_STEP_S`` of stream time, flushed at once. Each fix outcome is sent when the back-end has
    applied it. :meth:`finish` adds what only the finished run has: the final path, the landmark
    maps, the final trajectory's error and the matched pairs. The entities are those of
    :func:`write_rrd`; a viewer that goes away does not stop the run (rerun drops what it cannot
    send)."""

    def __init__(self, url: str, world: str, key: str, inputs, gt, recording_id: str | None = None) -> None:
        import rerun as rr

        self.world, self.key, self.gt = world, key, gt
        self.rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
        self.rec.connect_grpc(url, default_blueprint=blueprint([(world, [key], *_frame(inputs, gt, {}))]))
        log_world(self.rec, world, inputs, gt, {}, [])
        _log_styles(self.rec, world, key)
        self.rec.flush()
        self._last: tuple[float, np.ndarray] | None = None
        self.n_poses = self.n_fixes = 0

    def recorded(self, est) -> None:
        """A recorded online estimate (:class:`reloc.backend.PoseEstimate`): sent when it is
        ``RRD_STEP_M`` of path or ``LIVE_STEP_S`` past the last one sent."""
        from reloc.backend import Trajectory

        xy = np.asarray(est.position_m[:2], dtype=float)
        if self._last is not None:
            t0, xy0 = self._last
            if np.hypot(*(xy - xy0)) < RRD_STEP_M and est.t - t0 < LIVE_STEP_S:
                return
        self._last = (float(est.t), xy)
        one = Trajectory(np.array([est.t], dtype=float), np.asarray(est.T_world_base)[None], np.asarray(est.cov)[None])
        _log_online(self.rec, self.world, self.key, one, self.gt)
        self.rec.flush()
        self.n_poses += 1

    def fix(self, outcome) -> None:
        """A fix outcome, at its ``t_recv``."""
        _log_fixes(self.rec, self.world, self.key, [outcome])
        self.n_fixes += 1

    def finish(self, run) -> None:
        """The finished run (:class:`fgslam.runner.RunResult`): final path, maps, final error,
        matched pairs; then the stream is flushed and closed."""
        _log_run_result(self.rec, self.world, self.key, run, self.gt)
        _log_matches(self.rec, self.world, run.attempts)
        self.rec.flush()
        self.rec.disconnect()


def write_comparison_rrd(path: Path, comparisons: list) -> Path:
    """One recording for a whole comparison (a tab per world)."""
    return write_rrd(path, [(wc.inputs.name, wc.inputs, wc.gt, wc.runs, wc.attempts) for wc in comparisons])
