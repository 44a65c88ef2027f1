"""Stereo rock detector on the rover's mast camera.

Per frame: rocks within range whose centre projects into the 2304 x 1296 image are candidates; a
few rays from the camera to points spread over each candidate (batched over all frames, one
open3d ``cast_rays`` call per chunk) decide whether it is visible (enough rays hit that rock
first). A visible rock is detected with a probability that grows with its apparent size in pixels;
the logistic's offset is solved so the mean probability over all visible rocks equals the
configured recall. Positions get stereo noise (depth sigma = z^2 * sigma_disp / (f * baseline),
lateral sigma = z * sigma_px / f), reported with their covariance in base_link. False positives
(clutter on the terrain) are added so that true / all detections equals the configured precision.

Systematic errors (see :class:`sim.config.StereoConfig`): the error of each rock's centre estimate
(along the line of sight, a per-rock fraction of its radius: the pipeline moves the visible
surface back by a fixed share of the rock's size, and real rocks differ in shape), a per-run
rotation error of the camera mounting and a per-run depth scale error. They do not average out over frames,
which is what makes a real SLAM map drift and distort; white noise alone would not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.spatial import cKDTree

from sim.config import StereoConfig
from sim.errors import SimError
from sim.world import World

RAY_CHUNK = 400_000


@dataclass(frozen=True)
class StereoCamera:
    """Pinhole camera: ``f_px``, principal point, ``T_base_cam`` (4, 4) (optical frame: z forward,
    x right, y down)."""

    width_px: int
    height_px: int
    f_px: float
    T_base_cam: np.ndarray

    @staticmethod
    def from_config(cfg: StereoConfig) -> StereoCamera:
        f = 0.5 * cfg.width_px / np.tan(np.deg2rad(cfg.hfov_deg) / 2)
        R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical -> base axes
        th = np.deg2rad(cfg.mount_tilt_deg)
        Ry = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
        T = np.eye(4)
        T[:3, :3] = Ry @ R0
        T[:3, 3] = cfg.mount_xyz_m
        return StereoCamera(cfg.width_px, cfg.height_px, float(f), T)


@dataclass(frozen=True)
class StereoBias:
    """Systematic errors of one run: ``centre_frac`` (R,) per rock (fraction of its radius the
    centre estimate sits towards the camera; negative: behind the centre), ``R_cam_err`` (3, 3) the true camera rotation relative to
    the nominal mounting (optical frame), ``depth_scale`` the measured / true range ratio."""

    centre_frac: np.ndarray
    R_cam_err: np.ndarray
    depth_scale: float

    @staticmethod
    def draw(n_rocks: int, cfg: StereoConfig, rng: np.random.Generator) -> StereoBias:
        """Seeded draw of the run's systematic errors (no draw, so the stream of ``rng`` is untouched,
        when all three are off)."""
        terms = {"centre_error_frac": cfg.centre_error_frac, "extrinsic_sigma_deg": cfg.extrinsic_sigma_deg,
                 "depth_scale_sigma": cfg.depth_scale_sigma}
        bad = [f"{k}={v}" for k, v in terms.items() if not (np.isfinite(v) and v >= 0)]
        if bad:
            raise SimError(f"stereo systematic error settings must be finite and >= 0: {', '.join(bad)}")
        if not any(terms.values()):
            return StereoBias(np.zeros(n_rocks), np.eye(3), 1.0)
        frac = cfg.centre_error_frac * rng.standard_normal(n_rocks)
        ang = np.deg2rad(cfg.extrinsic_sigma_deg) * rng.standard_normal(3)
        scale = 1.0 + cfg.depth_scale_sigma * rng.standard_normal()
        return StereoBias(frac, _rotvec_matrix(ang), float(scale))


def _rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``w`` (3,) (Rodrigues)."""
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * K @ K


def biased_points(pc: np.ndarray, radius_m: np.ndarray, frac: np.ndarray, bias: StereoBias) -> np.ndarray:
    """Where stereo puts rock centres ``pc`` (M, 3) (nominal camera frame) before white noise:
    moved towards the camera by ``frac * radius_m`` (M,), seen through the mis-mounted camera
    and scaled in range. Returns (M, 3) in the nominal camera frame."""
    rng_m = np.linalg.norm(pc, axis=1, keepdims=True)
    u = pc / np.maximum(rng_m, 1e-9)
    near = pc - (frac * radius_m)[:, None] * u
    # the real camera is R_err-rotated from the nominal one: it sees R_err^T p; the pipeline
    # reports that as if it were taken in the nominal frame
    return bias.depth_scale * near @ bias.R_cam_err


@dataclass(frozen=True)
class StereoFrames:
    """Detections per frame (lists of length F): ``xyz_base_m`` (N, 3), ``cov_base_m2`` (N, 3, 3),
    ``size_m`` (N,), ``score`` (N,), ``rock`` (N,) the true rock row (-1: false positive); and
    ``visible`` the rock rows visible in each frame; ``bias`` the run's systematic errors."""

    xyz_base_m: list[np.ndarray]
    cov_base_m2: list[np.ndarray]
    size_m: list[np.ndarray]
    score: list[np.ndarray]
    rock: list[np.ndarray]
    visible: list[np.ndarray]
    bias: StereoBias | None = None  # the run's systematic errors

    @property
    def n_visible(self) -> int:
        return int(sum(len(v) for v in self.visible))

    @property
    def n_true(self) -> int:
        return int(sum(int(np.sum(r >= 0)) for r in self.rock))

    @property
    def n_detections(self) -> int:
        return int(sum(len(r) for r in self.rock))


def visible_rocks(world: World, T_world_base: np.ndarray, cfg: StereoConfig) -> tuple[np.ndarray, np.ndarray]:
    """Visible (frame, rock) pairs for camera poses from base poses ``T_world_base`` (F, 4, 4):
    returns ``frame`` (M,) and ``rock`` (M,) index arrays."""
    cam = StereoCamera.from_config(cfg)
    rocks = world.rocks
    F = len(T_world_base)
    if len(rocks) == 0 or F == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    T_wc = T_world_base @ cam.T_base_cam
    o = T_wc[:, :3, 3]
    tree = cKDTree(rocks.xyz_m[:, :2])
    lists = tree.query_ball_point(o[:, :2], cfg.max_range_m + 0.5)
    fr = np.repeat(np.arange(F), [len(x) for x in lists])
    rk = np.fromiter((k for x in lists for k in x), dtype=int, count=len(fr))
    R = T_wc[fr, :3, :3]
    pc = np.einsum("mji,mj->mi", R, rocks.xyz_m[rk] - o[fr])
    z = pc[:, 2]
    rng_m = np.linalg.norm(pc, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam.f_px * pc[:, 0] / z + cam.width_px / 2
        v = cam.f_px * pc[:, 1] / z + cam.height_px / 2
    keep = (z > cfg.min_range_m) & (rng_m < cfg.max_range_m) & (u >= 0) & (u < cam.width_px) & (v >= 0) & (v < cam.height_px)
    fr, rk, R = fr[keep], rk[keep], R[keep]
    if len(fr) == 0:
        return fr, rk
    # sample points: the centre and a ring across the line of sight, inside the rock's outline
    K = max(int(cfg.rays_per_rock), 1)
    ang = np.arange(K - 1) * 2 * np.pi / max(K - 1, 1)
    half_w = 0.45 * rocks.size_m[rk] / 2
    half_h = 0.45 * rocks.height_m[rk] / 2
    ex, ey = R[:, :, 0], np.array([0.0, 0.0, -1.0])  # camera right, world down
    offs = [np.zeros((len(rk), 3))]
    for a in ang:
        offs.append(np.cos(a) * half_w[:, None] * ex + np.sin(a) * half_h[:, None] * ey)
    q = rocks.xyz_m[rk][:, None, :] + np.stack(offs, axis=1)  # (M, K, 3)
    orig = np.broadcast_to(o[fr][:, None, :], q.shape)
    d = q - orig
    dist = np.linalg.norm(d, axis=2)
    rays = np.concatenate([orig, d / dist[..., None]], axis=2).reshape(-1, 6)
    scene = world.raycast_scene()
    hit_ok = np.zeros(len(rays), dtype=bool)
    target = np.repeat(rk, K)
    dist = dist.ravel()
    for s in range(0, len(rays), RAY_CHUNK):
        t_hit, rock_hit, _ = scene.cast(rays[s:s + RAY_CHUNK])
        sl = slice(s, s + RAY_CHUNK)
        hit_ok[sl] = (rock_hit == target[sl]) & (t_hit <= dist[sl] + 0.05)
    frac = hit_ok.reshape(-1, K).mean(axis=1)
    vis = frac >= cfg.min_visible_fraction
    return fr[vis], rk[vis]


def detection_probability(apparent_px: np.ndarray, recall: float, log_slope: float) -> np.ndarray:
    """p (M,) = sigmoid(a + log_slope * log(apparent_px)) with ``a`` solved so mean(p) = ``recall``."""
    if len(apparent_px) == 0 or recall >= 1.0:
        return np.ones(len(apparent_px))
    x = log_slope * np.log(np.maximum(apparent_px, 1e-3))

    def gap(a: float) -> float:
        return float(np.mean(1.0 / (1.0 + np.exp(-(a + x))))) - recall

    a = brentq(gap, -60.0 - x.max(), 60.0 - x.min(), xtol=1e-6)
    return 1.0 / (1.0 + np.exp(-(a + x)))


def _stereo_cov_cam(pc: np.ndarray, cam: StereoCamera, cfg: StereoConfig, sigma_extra_m: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame covariance (M, 3, 3): depth variance along the line of sight (plus
    ``sigma_extra_m`` (M,) there, the reported centre uncertainty), lateral across."""
    z = np.maximum(pc[:, 2], 0.1)
    s_r = z**2 * cfg.sigma_disparity_px / (cam.f_px * cfg.baseline_m)
    if sigma_extra_m is not None:
        s_r = np.sqrt(s_r**2 + sigma_extra_m**2)
    s_l = z * cfg.sigma_pixel_px / cam.f_px
    u = pc / np.linalg.norm(pc, axis=1, keepdims=True)
    return s_l[:, None, None] ** 2 * np.eye(3) + (s_r**2 - s_l**2)[:, None, None] * np.einsum("mi,mj->mij", u, u)


def simulate_stereo(world: World, T_world_base: np.ndarray, cfg: StereoConfig, rng: np.random.Generator,
                    bias: StereoBias | None = None) -> StereoFrames:
    """Rock detections for each base pose ``T_world_base`` (F, 4, 4) (one stereo frame each).
    ``bias``: the run's systematic errors (one entry of ``centre_frac`` per rock of ``world``);
    None draws them from ``rng``."""
    cam = StereoCamera.from_config(cfg)
    F = len(T_world_base)
    rocks = world.rocks
    if bias is None:
        bias = StereoBias.draw(len(rocks), cfg, rng)
    elif len(bias.centre_frac) != len(rocks):
        raise SimError(f"stereo bias has {len(bias.centre_frac)} rock centre errors for {len(rocks)} rocks")
    fr, rk = visible_rocks(world, T_world_base, cfg)
    T_wc = T_world_base @ cam.T_base_cam
    pc = np.einsum("mji,mj->mi", T_wc[fr, :3, :3], rocks.xyz_m[rk] - T_wc[fr, :3, 3])
    p_det = detection_probability(cam.f_px * rocks.size_m[rk] / np.maximum(pc[:, 2], 1e-3), cfg.recall, cfg.detect_log_slope)
    det = rng.random(len(fr)) < p_det
    # false positives: clutter points on the terrain in the lower part of the image
    n_fp = rng.poisson(det.sum() * (1.0 - cfg.precision) / cfg.precision) if cfg.precision < 1 else 0
    fp_frame, fp_pc = _clutter(world, T_wc, cam, cfg, n_fp, rng)
    frames = np.concatenate([fr[det], fp_frame])
    truth = np.concatenate([rk[det], np.full(len(fp_frame), -1)])
    pts = np.vstack([pc[det], fp_pc])
    lo, hi = np.log(cfg.fp_size_m[0]), np.log(cfg.fp_size_m[1])
    size_true = np.concatenate([rocks.size_m[rk[det]], np.exp(rng.uniform(lo, hi, len(fp_frame)))])
    radius = 0.5 * size_true
    # clutter is a patch of terrain, not a rock with a hidden centre: no centre error
    frac = np.concatenate([bias.centre_frac[rk[det]], np.zeros(len(fp_frame))])
    seen = biased_points(pts, radius, frac, bias) if len(pts) else pts
    sigma_centre = cfg.centre_error_frac * radius
    cov_c = _stereo_cov_cam(seen, cam, cfg, sigma_centre) if len(pts) else np.zeros((0, 3, 3))
    white = _stereo_cov_cam(seen, cam, cfg) if len(pts) and cfg.centre_error_frac > 0 else cov_c
    L = np.linalg.cholesky(white) if len(pts) else white
    meas_c = seen + np.einsum("mij,mj->mi", L, rng.standard_normal(pts.shape)) if len(pts) else pts
    Rbc, tbc = cam.T_base_cam[:3, :3], cam.T_base_cam[:3, 3]
    xyz_b = meas_c @ Rbc.T + tbc
    cov_b = np.einsum("ij,mjk,lk->mil", Rbc, cov_c, Rbc)
    cov_b = 0.5 * (cov_b + np.swapaxes(cov_b, 1, 2))
    size = size_true * np.exp(cfg.size_sigma_rel * rng.standard_normal(len(size_true)))
    score = np.where(truth >= 0, rng.beta(*cfg.score_true, len(truth)), rng.beta(*cfg.score_false, len(truth)))
    visible = [rk[fr == f] for f in range(F)]
    order = np.argsort(frames, kind="stable")
    bounds = np.searchsorted(frames[order], np.arange(F + 1))
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("xyz", "cov", "size", "score", "rock")}
    for f in range(F):
        sel = order[bounds[f]:bounds[f + 1]]
        out["xyz"].append(xyz_b[sel])
        out["cov"].append(cov_b[sel])
        out["size"].append(size[sel])
        out["score"].append(score[sel])
        out["rock"].append(truth[sel])
    return StereoFrames(out["xyz"], out["cov"], out["size"], out["score"], out["rock"], visible, bias)


def calibration_error_base(bias: StereoBias, cam: StereoCamera) -> tuple[np.ndarray, float]:
    """The run's mounting and scale errors as the back-ends' calibration sees them: the rotation
    vector (3,) rad of ``E`` with ``z_base ~ scale E q_base`` (base_link axes), and the scale."""
    R_bc = cam.T_base_cam[:3, :3]
    E = R_bc @ bias.R_cam_err.T @ R_bc.T
    c = float(np.clip((np.trace(E) - 1.0) / 2.0, -1.0, 1.0))
    th = float(np.arccos(c))
    v = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    w = 0.5 * v if th < 1e-9 else th / (2.0 * np.sin(th)) * v
    return w, bias.depth_scale


def _clutter(world: World, T_wc: np.ndarray, cam: StereoCamera, cfg: StereoConfig, n: int, rng: np.random.Generator):
    """``n`` false-positive points: (frame (n,), camera-frame xyz (n, 3)) on visible terrain."""
    F = len(T_wc)
    if n == 0 or F == 0:
        return np.zeros(0, dtype=int), np.zeros((0, 3))
    frames_out, pts_out = [], []
    need = n
    for _ in range(6):
        m = 3 * need + 16
        f = rng.integers(0, F, m)
        u = rng.uniform(0, cam.width_px, m)
        v = rng.uniform(0.3 * cam.height_px, cam.height_px, m)
        dc = np.column_stack([(u - cam.width_px / 2) / cam.f_px, (v - cam.height_px / 2) / cam.f_px, np.ones(m)])
        dc /= np.linalg.norm(dc, axis=1, keepdims=True)
        dw = np.einsum("mij,mj->mi", T_wc[f, :3, :3], dc)
        t_hit, rock, _ = world.raycast_scene().cast(np.hstack([T_wc[f, :3, 3], dw]))
        ok = (rock < 0) & np.isfinite(t_hit) & (t_hit > cfg.min_range_m) & (t_hit < cfg.max_range_m)
        idx = np.flatnonzero(ok)[:need]
        frames_out.append(f[idx])
        pts_out.append(dc[idx] * t_hit[idx, None] + np.array([0.0, -0.05, 0.0]))  # a little above ground
        need -= len(idx)
        if need == 0:
            break
    return np.concatenate(frames_out), np.vstack(pts_out)
