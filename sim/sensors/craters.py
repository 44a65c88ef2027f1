"""Crater rims seen by the rover's stereo (the simulator's statistical path).

Per frame and crater of the world (diameter >= ``min_diameter_m``): ``n_rim_samples`` points on the
rim circle (at the rim's mean terrain height) are in view when their horizontal range from the
camera is within [``min_range_m``, ``max_range_m``] and their bearing within half the horizontal
field of view; the crater is a candidate when at least ``min_completeness`` of its rim is in view
and the rim spans ``min_apparent_deg`` or more. A candidate is detected with probability
``recall_fresh (1 - degradation_penalty g)`` (g: the crater's degradation; worn rims are hard to
see). No occlusion is modelled: a crater is a depression, its rim stands above the plain.

The measured rim centre and diameter are those of a circle fit to the rim points in view
(:func:`reloc.craters.rim_fit_covariance`): ``visible arc length x rim_points_per_m`` points
(at most ``max_rim_points``), each with the stereo sigma at its range (depth
``z^2 sigma_disp / (f b)`` and lateral ``z sigma_px / f``, mean of the two squared: the radial
share of an arbitrary direction) plus the rim's irregularity ``irregularity_frac D``. A partial
rim (a crater larger than the view or reaching beyond the range) therefore gets a centre that
is uncertain along the arc's axis and a diameter uncertain with it, while a whole rim in view
gets the best of both. The reported covariance is that fit's, the measurement is drawn from it,
plus a per-crater systematic centre offset (``centre_bias_frac D``, fixed for the run: a rim's
shape does not average out over frames, it is in the reported covariance as well). The run's
stereo mounting rotation and depth scale errors (:class:`sim.sensors.stereo.StereoBias`) apply as
for rocks. There are no false craters: at ``min_completeness`` and above a rim is unambiguous.
"""

from __future__ import annotations

import numpy as np

from reloc.craters import CraterObservations, rim_fit_covariance
from sim.config import CraterSensorConfig, StereoConfig
from sim.sensors.stereo import StereoBias, StereoCamera, biased_points


def _rim_sigma2(r_m: np.ndarray, cam: StereoCamera, st: StereoConfig) -> np.ndarray:
    """Horizontal variance (...) m^2 of a stereo rim point at range ``r_m`` (...)."""
    depth = r_m**2 * st.sigma_disparity_px / (cam.f_px * st.baseline_m)
    lateral = r_m * st.sigma_pixel_px / cam.f_px
    return 0.5 * (depth**2 + lateral**2)


def crater_bias(seed: int, crater_id: np.ndarray) -> np.ndarray:
    """The per-crater systematic offsets (N, 3) of the rim centre (standard normal draws: x, y in
    units of ``centre_bias_frac D``, z of ``rim_height_sigma_frac D``), fixed for a run of
    ``seed`` whatever frames see the crater."""
    out = np.empty((len(crater_id), 3))
    for i, cid in enumerate(np.asarray(crater_id, dtype=np.int64)):
        out[i] = np.random.default_rng([seed, 301, int(cid) & 0xFFFFFFFF, int(cid) >> 32]).standard_normal(3)
    return out


def observe_craters(craters, rim_z_m: np.ndarray, T_world_base: np.ndarray, t: float, cfg: CraterSensorConfig,
                    st: StereoConfig, cam: StereoCamera, bias: StereoBias, bias_dir: np.ndarray,
                    rng: np.random.Generator) -> tuple[CraterObservations, np.ndarray]:
    """One frame's crater observation at base pose ``T_world_base`` (4, 4): ``craters``
    (:class:`sim.craters.Craters`, M) with rim heights ``rim_z_m`` (M,) and their offsets
    ``bias_dir`` (M, 3) (:func:`crater_bias`). Returns the observation and the ids (N,) of the
    craters it holds."""
    T_wc = T_world_base @ cam.T_base_cam
    cam_xy = T_wc[:2, 3]
    axis = T_wc[:3, 2]  # optical axis in world
    heading = np.arctan2(axis[1], axis[0])
    K = cfg.n_rim_samples
    a = np.linspace(0.0, 2 * np.pi, K, endpoint=False)
    D = craters.diameter_m
    rim = craters.xy_m[:, None, :] + 0.5 * D[:, None, None] * np.stack([np.cos(a), np.sin(a)], axis=1)[None]
    d = rim - cam_xy
    r = np.linalg.norm(d, axis=2)
    bearing = np.abs(np.angle(np.exp(1j * (np.arctan2(d[..., 1], d[..., 0]) - heading))))
    vis = (r >= cfg.min_range_m) & (r <= cfg.max_range_m) & (bearing <= np.deg2rad(st.hfov_deg) / 2)
    completeness = vis.mean(axis=1)
    centre_r = np.linalg.norm(craters.xy_m - cam_xy, axis=1)
    apparent = np.degrees(2 * np.arctan2(0.5 * D, np.maximum(centre_r, 1e-6)))
    cand = np.flatnonzero((completeness >= cfg.min_completeness) & (apparent >= cfg.min_apparent_deg))
    p = cfg.recall_fresh * (1.0 - cfg.degradation_penalty * craters.degradation[cand])
    det = cand[rng.random(len(cand)) < p]
    n = len(det)
    R_wb = T_world_base[:3, :3]
    xyz_b, cov_b = np.zeros((n, 3)), np.zeros((n, 3, 3))
    size, size_sigma = np.zeros(n), np.zeros(n)
    for j, m in enumerate(det):
        sel = vis[m]
        n_pts = int(np.clip(completeness[m] * np.pi * D[m] * cfg.rim_points_per_m, 3, cfg.max_rim_points))
        sig2 = _rim_sigma2(r[m, sel], cam, st) + (cfg.irregularity_frac * D[m]) ** 2
        # the K samples in view stand for n_pts rim points: information scales by n_pts / samples
        C = rim_fit_covariance(a[sel], np.sqrt(sig2)) * (sel.sum() / n_pts)
        C_xyz = np.zeros((3, 3))
        C_xyz[:2, :2] = C[:2, :2] + np.eye(2) * (cfg.centre_bias_frac * D[m]) ** 2
        C_xyz[2, 2] = float(np.mean(sig2)) / n_pts + (cfg.rim_height_sigma_frac * D[m]) ** 2
        centre_w = np.array([*(craters.xy_m[m] + cfg.centre_bias_frac * D[m] * bias_dir[m, :2]),
                             rim_z_m[m] + cfg.rim_height_sigma_frac * D[m] * bias_dir[m, 2]])
        pc = (centre_w - T_wc[:3, 3]) @ T_wc[:3, :3]
        seen_c = biased_points(pc[None], np.zeros(1), np.zeros(1), bias)[0]
        seen_b = cam.T_base_cam[:3, :3] @ seen_c + cam.T_base_cam[:3, 3]
        cov = R_wb.T @ C_xyz @ R_wb
        cov = 0.5 * (cov + cov.T)
        W = np.zeros((3, 3))  # the white part (the offsets are in centre_w already)
        W[:2, :2], W[2, 2] = C[:2, :2], float(np.mean(sig2)) / n_pts
        W = R_wb.T @ W @ R_wb
        xyz_b[j] = seen_b + np.linalg.cholesky(0.5 * (W + W.T)) @ rng.standard_normal(3)
        cov_b[j] = cov
        size_sigma[j] = 2.0 * np.sqrt(C[2, 2])
        size[j] = max(D[m] + size_sigma[j] * rng.standard_normal(), 0.25 * D[m])
    obs = CraterObservations(t, xyz_b, cov_b, size, size_sigma, np.maximum(completeness[det], 1.0 / K),
                             np.clip(0.5 + 0.5 * completeness[det], 0.0, 1.0))
    return obs, craters.id[det]
