"""From a constellation match to a global fix: the local map's selection, the rover-weighted
re-fit, and the fix with its covariance (see :mod:`fgslam.relocalizer` for the model).

The constellation matcher returns ``world = s * R(theta) @ local + t`` for the map snapshot taken
at ``t_meas``. Applied to the back-end's own pose estimate at that instant, it gives the rover's
global (x, y, yaw): ``xy = s R xy_est + t``, ``yaw = yaw_est + theta``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fgslam.relocalizer_config import RelocalizerConfig, RelocalizerError
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.covariance import psd_part
from reloc.geometry import wrap_angle
from reloc.measurements import CatalogAnchor, GlobalFix
from reloc.procrustes import rotation_2d


def select_local_map(lmap: LandmarkMap, xy_rover: np.ndarray, cfg: RelocalizerConfig,
                     min_size_m: float = 0.0, usable: np.ndarray | None = None) -> np.ndarray:
    """Indices of the landmarks used for matching: n_obs >= min_obs and size >= ``min_size_m``
    (and ``usable`` (N,) where given) within ``max_radius_m`` of the rover (``sparse_radius_m``
    where fewer than ``sparse_below`` are that near), at most ``max_landmarks`` of them, the
    largest (or the nearest, ``cfg.select``) first."""
    if len(lmap) == 0:
        return np.zeros(0, dtype=int)
    ok = (lmap.n_obs >= cfg.min_obs) & (lmap.size_m >= min_size_m)
    ok = np.flatnonzero(ok if usable is None else ok & np.asarray(usable, dtype=bool))
    d = np.linalg.norm(lmap.xyz_world_m[ok, :2] - np.asarray(xy_rover)[:2], axis=1)
    radius = cfg.max_radius_m
    if np.count_nonzero(d <= radius) < cfg.sparse_below:  # sparse ground: a wider map
        radius = max(radius, cfg.sparse_radius_m)
    ok, d = ok[d <= radius], d[d <= radius]
    if cfg.select == "largest":
        order = np.lexsort((d, -lmap.size_m[ok]))  # larger first, nearer among equals
    else:
        order = np.argsort(d, kind="stable")
    return np.sort(ok[order[: cfg.max_landmarks]])


def rover_relative_cov_xy(landmark_cov_xy: np.ndarray, rover_cov_xy: np.ndarray) -> np.ndarray:
    """(N, 2, 2): the uncertainty of the rover's planar position relative to each landmark that
    the rover has gained since the landmark was last seen: the positive part of ``rover_cov_xy``
    (2, 2) less the landmark's ``landmark_cov_xy`` (N, 2, 2), both in the world.

    A landmark is placed from the rover's poses, so its world covariance holds the rover's at the
    time it was seen (plus its measurements'); the two share that drift, which cancels between
    them. What the rover's covariance holds beyond it is the drift since: about 0 for a landmark
    in view (its covariance holds the rover's now), the drift while blind for one last seen before
    a camera blackout. An approximation where the joint covariance is not at hand (the smoother's
    map, landmarks a back-end has dropped): it takes the rover's growth since as uncorrelated
    with the landmark."""
    L = np.asarray(landmark_cov_xy, dtype=float).reshape(-1, 2, 2)
    D = np.asarray(rover_cov_xy, dtype=float)[None, :2, :2] - L
    return psd_part(D)


def fix_from_similarity(
    est: PoseEstimate,
    rotation_rad: float,
    translation: np.ndarray,
    scale: float,
    local_inliers_xy: np.ndarray,
    rmse_m: float,
    cfg: RelocalizerConfig,
    t_recv: float,
    map_var_m2: float = 0.0,
    similarity_cov: np.ndarray | None = None,
    cov_scale: float = 1.0,
    relative_cov_xy: np.ndarray | None = None,
    catalog_rows: np.ndarray | None = None,
    source: str = "",
) -> GlobalFix:
    """Rover fix at ``est.t`` from a local->world similarity and its inliers (K, 2) in the local (estimated world) frame.

    With ``similarity_cov`` (4, 4) over (tx_m, ty_m, theta_rad, scale) from the matcher, the fix
    covariance is its first-order propagation through xy = s R xy_est + t, yaw = yaw_est + theta
    (times ``inflation``^2, plus the map term); otherwise the inlier-geometry formula of the
    module doc is used. ``relative_cov_xy`` (2, 2): the rover's uncertainty relative to the
    inliers (:func:`rover_relative_cov_xy`, weighted as in the fit), added to the position's:
    one drift that every inlier shares, so it does not average down."""
    L = np.asarray(local_inliers_xy, float).reshape(-1, 2)
    n = L.shape[0]
    if n < 3:
        raise RelocalizerError(f"a fix needs at least 3 inliers, got {n}")
    c, s = np.cos(rotation_rad), np.sin(rotation_rad)
    R = np.array([[c, -s], [s, c]])
    t = np.asarray(translation, float).reshape(2)
    xy_est = est.position_m[:2]
    xy = scale * R @ xy_est + t
    yaw = float(wrap_angle(est.yaw_rad + rotation_rad))
    dof_corr = n / max(n - 4, 1)  # 4 fitted parameters (similarity) shrink the residuals
    sigma2 = max(rmse_m**2 * dof_corr + cfg.map_cov_weight * map_var_m2, cfg.sigma_floor_m**2)
    sigma2 *= cfg.inflation**2
    centroid = L.mean(axis=0)
    spread = float(np.sum((L - centroid) ** 2))
    var_yaw = max(sigma2 / max(spread, 1e-9), cfg.sigma_yaw_floor_rad**2)
    d_world = R @ (xy_est - centroid)
    perp = np.array([-d_world[1], d_world[0]])
    cov = np.zeros((3, 3))
    if similarity_cov is not None and np.all(np.isfinite(similarity_cov)):
        J = np.zeros((3, 4))
        J[:2, :2] = np.eye(2)
        J[:2, 2] = scale * np.array([[-s, -c], [c, -s]]) @ xy_est
        J[:2, 3] = R @ xy_est
        J[2, 2] = 1.0
        cov = cfg.inflation**2 * (J @ np.asarray(similarity_cov, float) @ J.T)
        cov[:2, :2] += (cfg.inflation**2 * cfg.map_cov_weight * map_var_m2 / n + cfg.sigma_floor_m**2 / n) * np.eye(2)
        cov[2, 2] = max(cov[2, 2], cfg.sigma_yaw_floor_rad**2)
        cov = 0.5 * (cov + cov.T)
    else:
        cov[:2, :2] = sigma2 / n * np.eye(2) + var_yaw * np.outer(perp, perp)
        cov[:2, 2] = cov[2, :2] = var_yaw * perp
        cov[2, 2] = var_yaw
    cov = cov * cov_scale
    rel = None
    if relative_cov_xy is not None:  # the rover's drift from its map: no catalog error to scale
        rel = 0.5 * (np.asarray(relative_cov_xy, float) + np.transpose(relative_cov_xy))
        cov[:2, :2] += rel
    return GlobalFix(
        t_meas=est.t, t_recv=t_recv, x_m=float(xy[0]), y_m=float(xy[1]), yaw_rad=yaw,
        cov_xyyaw=cov, n_inliers=n, rmse_m=float(rmse_m), correlation_scale=cov_scale, cov_relative_xy=rel,
        catalog_rows=() if catalog_rows is None else tuple(np.asarray(catalog_rows, int).tolist()), source=source,
    )


def rover_weights(xy: np.ndarray, rover_xy: np.ndarray, radius_m: float | None) -> np.ndarray:
    """(K,) weights of map points ``xy`` (K, 2) by closeness to the rover, ``w = 1 / (1 + (d /
    radius_m)^2)`` (``RelocalizerConfig.fit_radius_m``; None: all 1)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    if radius_m is None:
        return np.ones(len(xy))
    return 1.0 / (1.0 + np.sum((xy - np.asarray(rover_xy, float)[:2]) ** 2, axis=1) / radius_m**2)


def rover_weighted_fit(
    local_xy: np.ndarray, world_xy: np.ndarray, rover_xy: np.ndarray, radius_m: float, floor_sigma_m: float
):
    """Rigid re-fit of matched pairs (K, 2) weighted by closeness to the rover, ``w = 1 / (1 +
    (d / radius_m)^2)`` (``RelocalizerConfig.fit_radius_m``): (rotation_rad, translation (2,),
    scale 1, weighted RMSE m, (4, 4) covariance over (tx, ty, theta, scale), residual sigma
    floored at ``floor_sigma_m``)."""
    from reloc.match_result import similarity_covariance
    from reloc.procrustes import umeyama_2d

    w = rover_weights(local_xy, rover_xy, radius_m)
    sim = umeyama_2d(local_xy, world_xy, w, with_scale=False)
    res = sim.apply(local_xy) - world_xy
    rmse = float(np.sqrt(np.sum(w * np.sum(res * res, axis=1)) / np.sum(w)))
    cov = similarity_covariance(sim, local_xy, world_xy, floor_sigma_m=floor_sigma_m, with_scale=False, weights=w)
    return float(sim.theta_rad), np.asarray(sim.translation, float), 1.0, rmse, cov


@dataclass(frozen=True)
class SingleIdentification:
    """One mapped landmark (index ``landmark`` into the map) identified with catalog row ``row``:
    its squared Mahalanobis distance ``d2`` in the gate and ``false_alarm``, the odds that an
    entry of compatible size lies that close by chance rather than being the landmark itself."""

    landmark: int
    row: int
    d2: float
    false_alarm: float


def _size_compatible(rows: np.ndarray, catalog_size: np.ndarray, size: float, size_ratio_max: float | None) -> np.ndarray:
    """The catalog ``rows`` whose diameter is within ``size_ratio_max`` of ``size`` (all for None)."""
    if size_ratio_max is None:
        return rows
    cs = catalog_size[rows]
    return rows[np.maximum(cs, size) / np.maximum(np.minimum(cs, size), 1e-9) <= size_ratio_max]


def _within(lmap: LandmarkMap, idx: np.ndarray, xy_rover: np.ndarray, radius_m: float) -> list[int]:
    """The landmarks of ``idx`` within ``radius_m`` of the rover's planar position ``xy_rover``."""
    xy_rover = np.asarray(xy_rover, float)[:2]
    return [int(i) for i in np.asarray(idx, dtype=int) if np.hypot(*(lmap.xyz_world_m[i, :2] - xy_rover)) <= radius_m]


def catalog_sigma(cfg: RelocalizerConfig, sigma_m: float, size_m) -> np.ndarray | float:
    """Per-axis sigma of a catalog entry of size ``size_m`` (scalar or array): the matcher's
    ``sigma_m``, and ``cfg.catalog_sigma_rel`` of the size where that is more (in quadrature)."""
    return np.hypot(sigma_m, cfg.catalog_sigma_rel * np.asarray(size_m, float))


class _Gate(NamedTuple):
    """A landmark's own gate (:func:`_own_gate`) with the chance density around it and the
    catalog sigma it was drawn with."""

    rows: np.ndarray
    d2: np.ndarray
    rho: float
    S: np.ndarray
    sigma_m: float


def _own_gate(lmap: LandmarkMap, i: int, catalog_xy: np.ndarray, catalog_size: np.ndarray, tree,
              cfg: RelocalizerConfig, sigma_m: float, size_ratio_max: float | None,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Landmark ``i``'s own gate: its planar world covariance plus the catalog's sigma per axis
    at the landmark's size (:func:`catalog_sigma`; its entries are size-compatible) ``S`` (2, 2),
    the size-compatible catalog rows inside it (chi-square ``single_gate_chi2``) with their
    squared Mahalanobis distances, and that sigma; None when ``S`` is not a covariance or the gate
    reaches beyond ``single_density_radius_m`` (the disc its chance density is counted on, which
    would then not describe the gate)."""
    sigma_c = float(catalog_sigma(cfg, sigma_m, lmap.size_m[i]))
    S = 0.5 * (lmap.cov_world_m2[i, :2, :2] + lmap.cov_world_m2[i, :2, :2].T) + sigma_c ** 2 * np.eye(2)
    if not np.all(np.isfinite(S)) or np.linalg.det(S) <= 0.0:
        return None
    l_xy = lmap.xyz_world_m[i, :2]
    reach = float(np.sqrt(cfg.single_gate_chi2 * np.linalg.eigvalsh(S)[-1]))
    if reach > cfg.single_density_radius_m:
        return None
    rows = _size_compatible(np.asarray(tree.query_ball_point(l_xy, reach), dtype=int), catalog_size,
                            float(lmap.size_m[i]), size_ratio_max)
    d = catalog_xy[rows] - l_xy
    d2 = np.einsum("ki,ij,kj->k", d, np.linalg.inv(S), d) if len(rows) else np.zeros(0)
    inside = d2 <= cfg.single_gate_chi2
    return S, rows[inside], d2[inside], sigma_c


def _chance_density(lmap: LandmarkMap, i: int, catalog_size: np.ndarray, tree, cfg: RelocalizerConfig,
                    sigma_m: float, size_ratio_max: float | None, box: tuple[float, float, float, float]) -> float:
    """Chance entries per m^2 around landmark ``i``: the size-compatible entries within
    ``single_density_radius_m`` (the candidate counted) over the part of that disc inside the
    catalog's bounding box ``box`` (a small catalog, a yard's, counted over the whole disc would
    look far sparser than it is)."""
    l_xy = lmap.xyz_world_m[i, :2]
    near = np.asarray(tree.query_ball_point(l_xy, cfg.single_density_radius_m), dtype=int)
    n_near = len(_size_compatible(near, catalog_size, float(lmap.size_m[i]), size_ratio_max))
    return n_near / max(disc_box_area(l_xy, cfg.single_density_radius_m, box), np.pi * sigma_m ** 2)


def identify_single(lmap: LandmarkMap, idx: np.ndarray, xy_rover: np.ndarray, catalog_xy: np.ndarray,
                    catalog_size: np.ndarray, tree, cfg: RelocalizerConfig, sigma_m: float,
                    size_ratio_max: float | None, catalog_box: tuple[float, float, float, float] | None = None,
                    ) -> SingleIdentification | None:
    """The landmark among ``idx`` (within ``cfg.single_radius_m`` of ``xy_rover``) that one
    catalog entry alone explains (see ``RelocalizerConfig.single_landmark``), the one with the
    smallest false-alarm bound; None when no landmark passes. ``tree`` is a KD-tree of
    ``catalog_xy`` (scipy's ``cKDTree``); ``size_ratio_max`` None: no size check (the matcher's);
    ``catalog_box`` the catalog's (xmin, ymin, xmax, ymax) (:func:`catalog_box_of`; None: computed)."""
    best: SingleIdentification | None = None
    box = catalog_box_of(catalog_xy) if catalog_box is None else catalog_box
    for i in _within(lmap, idx, xy_rover, cfg.single_radius_m):
        gate = _own_gate(lmap, i, catalog_xy, catalog_size, tree, cfg, sigma_m, size_ratio_max)
        if gate is None or len(gate[1]) != 1:  # nothing there, or ambiguous
            continue
        S, rows, d2, _ = gate
        rho = _chance_density(lmap, i, catalog_size, tree, cfg, sigma_m, size_ratio_max, box)
        false_alarm = _chance_odds(rho, S, float(d2[0]))
        if false_alarm > cfg.single_max_false_alarm:
            continue
        if best is None or false_alarm < best.false_alarm:
            best = SingleIdentification(int(i), int(rows[0]), float(d2[0]), float(false_alarm))
    return best


@dataclass(frozen=True)
class PairIdentification:
    """Two mapped landmarks (indices ``landmarks`` into the map) identified together with catalog
    rows ``rows``: ``d2`` the first's squared Mahalanobis distance in its own gate, ``d2_rel`` the
    pair's separation against the entries', and ``false_alarm`` the odds that chance entries
    explain both (:func:`identify_pair`)."""

    landmarks: tuple[int, int]
    rows: tuple[int, int]
    d2: float
    d2_rel: float
    false_alarm: float


def _chance_odds(rho_per_m2: float, S: np.ndarray, d2: float) -> float:
    """The odds that a chance entry (``rho_per_m2`` of them per m^2) lies at squared Mahalanobis
    distance ``d2`` in gate ``S`` (2, 2) rather than the landmark's own entry: rho / N(d; 0, S)."""
    return rho_per_m2 * 2.0 * np.pi * float(np.sqrt(max(np.linalg.det(S), 0.0))) * float(np.exp(0.5 * d2))


def identify_pair(lmap: LandmarkMap, idx: np.ndarray, xy_rover: np.ndarray, catalog_xy: np.ndarray,
                  catalog_size: np.ndarray, tree, cfg: RelocalizerConfig, sigma_m: float,
                  size_ratio_max: float | None, catalog_box: tuple[float, float, float, float] | None = None,
                  ) -> PairIdentification | None:
    """Two landmarks among ``idx`` (within ``cfg.pair_radius_m`` of ``xy_rover``, or
    ``cfg.single_radius_m`` where that is None) that two
    catalog entries explain together (``RelocalizerConfig.pair_landmarks``); the pair with the
    smallest false-alarm bound, or None.

    Each landmark's candidates are the size-compatible entries inside its own gate (its world
    covariance plus ``sigma_m`` per axis, chi-square ``single_gate_chi2``), as for one landmark;
    a candidate pair of entries must also reproduce the landmarks' separation within the gate
    of their relative error (the part of their world covariances not shared, ``sigma_floor_m``
    each at least, plus both entries' ``sigma_m``), which the rover's drift does not widen. The
    pair is identified when exactly one pair of entries passes both, and the odds that chance
    entries explain it (a chance entry in the wider of the two own gates, times a chance entry
    in the separation's gate, each as :func:`identify_single` counts them), times the number of
    pairs the map offers (a union bound over them), are at most ``single_max_false_alarm``: where
    one rock of a sparse yard is not identifiable alone (its own gate holds the rover's drift),
    the separation's gate is a few decimetres wide."""
    box = catalog_box_of(catalog_xy) if catalog_box is None else catalog_box
    radius_m = cfg.single_radius_m if cfg.pair_radius_m is None else cfg.pair_radius_m
    near_rover = _within(lmap, idx, xy_rover, radius_m)
    gates: dict[int, _Gate] = {}
    for i in near_rover:
        gate = _own_gate(lmap, i, catalog_xy, catalog_size, tree, cfg, sigma_m, size_ratio_max)
        if gate is not None and len(gate[1]):
            S, rows, d2, sigma_c = gate
            gates[i] = _Gate(rows, d2, _chance_density(lmap, i, catalog_size, tree, cfg, sigma_m, size_ratio_max, box), S,
                             sigma_c)
    if len(gates) < 2:
        return None
    n_pairs = len(near_rover) * (len(near_rover) - 1) // 2  # every pair is a chance to be fooled

    def white2(gi: _Gate, gj: _Gate) -> np.ndarray:  # the separation's gate at its narrowest: floors and entries
        return (2.0 * cfg.sigma_floor_m ** 2 + gi.sigma_m ** 2 + gj.sigma_m ** 2) * np.eye(2)

    # the smallest bound any pair could reach (own gates at d2 = 0, the narrowest separation gate):
    # above the limit, no pair can pass (a dense catalog: decided before the pairs are looked at)
    narrowest = min(gates.values(), key=lambda g: g.sigma_m)
    lowest = (n_pairs * min(_chance_odds(g.rho, g.S, 0.0) for g in gates.values())
              * _chance_odds(min(g.rho for g in gates.values()), white2(narrowest, narrowest), 0.0))
    if lowest > cfg.single_max_false_alarm:
        return None
    best: PairIdentification | None = None
    keys = sorted(gates)
    for a_pos, i in enumerate(keys):
        for j in keys[a_pos + 1:]:
            gi, gj = gates[i], gates[j]
            u = lmap.xyz_world_m[j, :2] - lmap.xyz_world_m[i, :2]
            S_rel = psd_part(lmap.cov_world_m2[j, :2, :2] - lmap.cov_world_m2[i, :2, :2]) + white2(gi, gj)
            W_rel = np.linalg.inv(S_rel)
            e = catalog_xy[gj.rows][None, :, :] - catalog_xy[gi.rows][:, None, :] - u  # (n_i, n_j, 2)
            d2_rel = np.einsum("abi,ij,abj->ab", e, W_rel, e)
            ok = (d2_rel <= cfg.single_gate_chi2) & (gi.rows[:, None] != gj.rows[None, :])
            if np.count_nonzero(ok) != 1:  # nothing, or ambiguous
                continue
            a, b = (int(v[0]) for v in np.nonzero(ok))
            first = max(_chance_odds(gi.rho, gi.S, float(gi.d2[a])), _chance_odds(gj.rho, gj.S, float(gj.d2[b])))
            false_alarm = n_pairs * first * _chance_odds(max(gi.rho, gj.rho), S_rel, float(d2_rel[a, b]))
            if false_alarm > cfg.single_max_false_alarm:
                continue
            if best is None or false_alarm < best.false_alarm:
                best = PairIdentification((i, j), (int(gi.rows[a]), int(gj.rows[b])), float(gi.d2[a]),
                                          float(d2_rel[a, b]), float(false_alarm))
    return best


def fix_from_pair(est: PoseEstimate, landmarks_xy: np.ndarray, relative_cov_xy: np.ndarray, catalog_xy: np.ndarray,
                  cfg: RelocalizerConfig, sigma_m: float | np.ndarray, t_recv: float, cov_scale: float = 1.0,
                  catalog_rows: tuple[int, int] | None = None, source: str = "",
                  anchors: tuple[CatalogAnchor, ...] = ()) -> GlobalFix:
    """Planar fix (x, y, yaw) at ``est.t`` from two landmarks ``landmarks_xy`` (2, 2, estimated
    world) identified with catalog entries ``catalog_xy`` (2, 2): the rigid motion that puts the
    landmarks' midpoint on the entries' and their direction on theirs, applied to the estimate.

    Its covariance is the first-order image (central differences over the eight coordinates) of
    the entries' ``sigma_m`` per axis (one for both, or one each: :func:`catalog_sigma`) and
    each landmark's error relative to the rover
    (``relative_cov_xy`` (2, 2, 2), :func:`rover_relative_cov_xy`, never below ``sigma_floor_m``),
    times ``inflation``^2 as a matched fix's: the heading is as good as the pair is long.
    ``anchors``: the two identifications, for a back-end that puts them on its landmarks."""
    L = np.asarray(landmarks_xy, float).reshape(2, 2)
    C = np.asarray(catalog_xy, float).reshape(2, 2)
    xy_est, yaw_est = np.asarray(est.position_m, float)[:2], float(est.yaw_rad)

    def pose(p: np.ndarray) -> np.ndarray:
        l, c = p[:4].reshape(2, 2), p[4:].reshape(2, 2)
        u, v = l[1] - l[0], c[1] - c[0]
        th = np.arctan2(v[1], v[0]) - np.arctan2(u[1], u[0])
        return np.r_[rotation_2d(th) @ (xy_est - l.mean(axis=0)) + c.mean(axis=0), th]

    p0 = np.r_[L.ravel(), C.ravel()]
    J = np.zeros((3, 8))
    h = 1e-6
    for k in range(8):
        dp = np.zeros(8)
        dp[k] = h
        a, b = pose(p0 + dp), pose(p0 - dp)
        J[:, k] = np.r_[a[:2] - b[:2], wrap_angle(a[2] - b[2])] / (2 * h)
    P = np.zeros((8, 8))
    for k in range(2):
        P[2 * k:2 * k + 2, 2 * k:2 * k + 2] = psd_part(np.asarray(relative_cov_xy, float)[k], cfg.sigma_floor_m ** 2)
    P[4:, 4:] = np.diag(np.repeat(np.broadcast_to(np.asarray(sigma_m, float) ** 2, (2,)), 2))
    cov = cfg.inflation ** 2 * (J @ P @ J.T)
    out = pose(p0)
    return GlobalFix(t_meas=est.t, t_recv=t_recv, x_m=float(out[0]), y_m=float(out[1]),
                     yaw_rad=float(wrap_angle(yaw_est + out[2])), cov_xyyaw=0.5 * (cov + cov.T) * cov_scale,
                     n_inliers=2, rmse_m=0.0, correlation_scale=cov_scale,
                     catalog_rows=() if catalog_rows is None else tuple(int(r) for r in catalog_rows), source=source,
                     anchors=anchors)


def catalog_box_of(catalog_xy: np.ndarray) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of a catalog's entries (all zero for an empty one)."""
    xy = np.asarray(catalog_xy, float).reshape(-1, 2)
    if not len(xy):
        return (0.0, 0.0, 0.0, 0.0)
    return (*map(float, xy.min(axis=0)), *map(float, xy.max(axis=0)))


def disc_box_area(center_xy, radius_m: float, box: tuple[float, float, float, float], n: int = 512) -> float:
    """Area (m^2) of the disc (``center_xy``, ``radius_m``) inside the box ``(xmin, ymin, xmax,
    ymax)``: the disc's chords clipped to the box, summed over ``n`` strips (midpoint rule, error
    well under 1 % for n = 512)."""
    cx, cy = float(center_xy[0]), float(center_xy[1])
    x0, x1 = max(cx - radius_m, box[0]), min(cx + radius_m, box[2])
    if x1 <= x0:
        return 0.0
    w = (x1 - x0) / n
    x = x0 + (np.arange(n) + 0.5) * w
    h = np.sqrt(np.maximum(radius_m**2 - (x - cx) ** 2, 0.0))
    chord = np.clip(np.minimum(cy + h, box[3]) - np.maximum(cy - h, box[1]), 0.0, None)
    return float(chord.sum() * w)


def fix_from_single(est: PoseEstimate, landmark_xy: np.ndarray, landmark_cov_xy: np.ndarray,
                    catalog_xy: np.ndarray, cfg: RelocalizerConfig, sigma_m: float, t_recv: float,
                    cov_scale: float = 1.0, catalog_row: int | None = None, source: str = "",
                    anchors: tuple[CatalogAnchor, ...] = ()) -> GlobalFix:
    """Position fix at ``est.t`` from one landmark identified with a catalog entry: the rover
    moved by what puts the landmark on the entry, ``xy = xy_est + (catalog - landmark)``; the
    heading stays the estimate's with ``single_sigma_yaw_rad`` (no heading information).

    Its planar covariance is the entry's ``sigma_m`` per axis (:func:`catalog_sigma`) plus the landmark's error
    relative to the rover, taken as the difference of its world covariance and the rover's,
    either way (the landmark is placed from the rover's poses, so their shared drift cancels;
    what the landmark holds beyond the rover is its own error, what the rover holds beyond the
    landmark its drift since it was last seen, :func:`rover_relative_cov_xy`; never below
    ``sigma_floor_m``), times ``inflation``^2 as a matched fix's (unmodelled errors of the rim's
    centre on both sides). ``anchors``: the identification, for a back-end that puts it on its landmark."""
    rel = np.asarray(landmark_cov_xy, float) - np.asarray(est.cov[:2, :2], float)
    w, V = np.linalg.eigh(0.5 * (rel + rel.T))
    rel = (V * np.maximum(np.abs(w), cfg.sigma_floor_m ** 2)) @ V.T
    cov = np.zeros((3, 3))
    cov[:2, :2] = cfg.inflation ** 2 * (sigma_m ** 2 * np.eye(2) + rel)
    cov[2, 2] = cfg.single_sigma_yaw_rad ** 2
    xy = est.position_m[:2] + (np.asarray(catalog_xy, float) - np.asarray(landmark_xy, float))
    return GlobalFix(t_meas=est.t, t_recv=t_recv, x_m=float(xy[0]), y_m=float(xy[1]), yaw_rad=float(est.yaw_rad),
                     cov_xyyaw=cov * cov_scale, n_inliers=1, rmse_m=0.0, correlation_scale=cov_scale,
                     catalog_rows=() if catalog_row is None else (int(catalog_row),), source=source, anchors=anchors)
