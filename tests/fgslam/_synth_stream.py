"""A small seeded synthetic traverse for the application-layer tests (no simulator needed).

A rover drives a gentle S-curve through a uniform rock field; commands are scaled by a slip
factor so dead reckoning drifts; the IMU yaw has a gyro bias; a forward stereo sensor sees rocks
within range with noise; the catalog is the true rocks with orbital noise and misses. A
nearest-neighbour + Kabsch matcher stands in for the constellation matcher where needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from fgslam.inputs import RunInputs, start_pose_from_truth
from reloc.craters import CraterObservations, rim_fit_covariance
from reloc.measurements import (
    CmdVel,
    GroundTruthPose,
    ImuSample,
    RockCatalog,
    RockObservations,
    sort_key,
)


def make_stream(seed: int = 0, duration_s: float = 60.0, speed_mps: float = 0.25, slip: float = 0.95,
                gyro_bias_radps: float = 0.002, field_m: float = 40.0, density_per_m2: float = 0.25,
                sigma_obs_m: float = 0.03, catalog_sigma_m: float = 0.03, craters: bool = False,
                rocks_on: bool = True) -> RunInputs:
    """Seeded inputs: 30 Hz cmd/IMU/truth, 2 Hz rock frames; the start is at (-8, -8) heading +x.
    ``craters``: also a crater field (its own random stream: the rocks' draws are unchanged),
    0.5 Hz crater frames (:func:`crater_frame`) and a crater catalog; ``rocks_on`` False leaves
    the rock frames out (a crater-only run)."""
    rng = np.random.default_rng(seed)
    crater_field = CraterField.draw(seed, 3 * field_m) if craters else None
    n_rocks = int(density_per_m2 * field_m**2)
    rocks = rng.uniform(-field_m / 2, field_m / 2, (n_rocks, 2))
    sizes = np.clip(0.1 * (1 - rng.uniform(0, 1, n_rocks)) ** (-1 / 2.0), 0.1, 1.5)
    dt = 1.0 / 30.0
    n = int(duration_s / dt) + 1
    t = np.arange(n) * dt
    w_cmd = 0.04 * np.sin(2 * np.pi * t / 40.0)
    x, y, yaw = -8.0, -8.0, 0.0
    meas: list = []
    yaw_imu = 0.0
    for k in range(n):
        tk = float(t[k])
        if k:
            v_true = speed_mps * slip
            yaw += w_cmd[k - 1] * dt
            x += v_true * dt * np.cos(yaw)
            y += v_true * dt * np.sin(yaw)
            yaw_imu += (w_cmd[k - 1] + gyro_bias_radps) * dt
        meas.append(CmdVel(tk, speed_mps, float(w_cmd[k])))
        meas.append(ImuSample(tk, Rotation.from_euler("z", yaw_imu).as_quat(), np.array([0, 0, w_cmd[k]])))
        meas.append(GroundTruthPose(tk, np.array([x, y, 0.0]), Rotation.from_euler("z", yaw).as_quat()))
        if k % 15 == 0:
            c, s = np.cos(yaw), np.sin(yaw)
            d = rocks - [x, y]
            local = d @ np.array([[c, -s], [s, c]])  # world -> base
            rng_m = np.linalg.norm(local, axis=1)
            vis = (local[:, 0] > 0.5) & (rng_m < 8.0) & (np.abs(np.arctan2(local[:, 1], local[:, 0])) < 0.8)
            vis &= rng.uniform(0, 1, n_rocks) < 0.85
            m = int(vis.sum())
            xyz = np.column_stack([local[vis], np.zeros(m)]) + rng.normal(0, sigma_obs_m, (m, 3))
            cov = np.tile(np.eye(3) * sigma_obs_m**2, (m, 1, 1))
            if rocks_on:
                meas.append(RockObservations(tk, xyz, cov, sizes[vis] * rng.uniform(0.9, 1.1, m), np.full(m, 0.9)))
        if crater_field is not None and k % 60 == 0:
            meas.append(crater_field.frame(tk, x, y, yaw))
    meas.sort(key=sort_key)
    keep = rng.uniform(0, 1, n_rocks) < 0.8
    catalog = RockCatalog(rocks[keep] + rng.normal(0, catalog_sigma_m, (int(keep.sum()), 2)), sizes[keep],
                          np.full(int(keep.sum()), 0.5))
    gt0 = next(m for m in meas if isinstance(m, GroundTruthPose))
    img = (rng.uniform(0, 1, (64, 64, 3)) * 255).astype(np.uint8)
    catalogs = {"rocks": catalog}
    if crater_field is not None:
        catalogs["craters"] = crater_field.catalog()
    return RunInputs(name=f"synth{seed}", measurements=meas, catalogs=catalogs, initial=start_pose_from_truth(gt0),
                     orbital_image=img, orbital_extent=(-field_m / 2, field_m / 2, -field_m / 2, field_m / 2),
                     rocks_true_xy=rocks, source={"kind": "synthetic", "seed": seed})


class CraterField:
    """Craters of 2-8 m on flat ground, seen by a forward stereo within 25 m and +-40 deg: each a
    circle fit of the rim points in view (:func:`reloc.craters.rim_fit_covariance`, 0.1 m per
    point, 2 points per metre of rim), its centre and diameter drawn from that covariance."""

    def __init__(self, xy: np.ndarray, d: np.ndarray, rng: np.random.Generator) -> None:
        self.xy, self.d, self.rng = xy, d, rng

    @staticmethod
    def draw(seed: int, extent_m: float, density_per_m2: float = 0.02) -> CraterField:
        rng = np.random.default_rng([seed, 15])
        n = int(density_per_m2 * extent_m**2)
        return CraterField(rng.uniform(-extent_m / 2, extent_m / 2, (n, 2)), rng.uniform(2.0, 8.0, n), rng)

    def frame(self, t: float, x: float, y: float, yaw: float) -> CraterObservations:
        a = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        c, s = np.cos(yaw), np.sin(yaw)
        Rwb = np.array([[c, -s], [s, c]])
        xyz, cov, size, sig, comp = [], [], [], [], []
        for j in range(len(self.xy)):
            rim = self.xy[j] + 0.5 * self.d[j] * np.column_stack([np.cos(a), np.sin(a)]) - [x, y]
            loc = rim @ Rwb
            r = np.linalg.norm(loc, axis=1)
            vis = (r > 1.0) & (r < 25.0) & (np.abs(np.arctan2(loc[:, 1], loc[:, 0])) < np.deg2rad(40))
            if vis.mean() < 0.3:
                continue
            n_pts = max(int(vis.mean() * np.pi * self.d[j] * 2.0), 3)
            C = rim_fit_covariance(a[vis], 0.1) * (vis.sum() / n_pts)
            Cw = np.zeros((3, 3))
            Cw[:2, :2], Cw[2, 2] = C[:2, :2], 0.01
            e = np.linalg.cholesky(Cw) @ self.rng.standard_normal(3)
            R3 = np.eye(3)
            R3[:2, :2] = Rwb
            xyz.append(np.array([*((self.xy[j] - [x, y]) @ Rwb), 0.0]) + R3.T @ e)
            cov.append(R3.T @ Cw @ R3)
            sig.append(2.0 * np.sqrt(C[2, 2]))
            size.append(self.d[j] + sig[-1] * self.rng.standard_normal())
            comp.append(vis.mean())
        n = len(xyz)
        return CraterObservations(t, np.reshape(xyz, (n, 3)), np.reshape(cov, (n, 3, 3)), np.maximum(size, 0.5),
                                  np.array(sig), np.array(comp), np.full(n, 0.9))

    def catalog(self, sigma_m: float = 0.15) -> RockCatalog:
        rng = np.random.default_rng(1)
        return RockCatalog(self.xy + rng.normal(0, sigma_m, self.xy.shape), self.d * np.exp(0.05 * rng.standard_normal(len(self.d))),
                           np.full(len(self.d), 0.8))


@dataclass(frozen=True)
class _Match:
    rotation_rad: float
    translation: np.ndarray
    scale: float
    inlier_pairs: np.ndarray
    rmse_m: float


class NearestNeighbourMatcher:
    """Iterated nearest-neighbour association + Kabsch (valid for small drift): the tests' matcher."""

    def __init__(self, catalog_xy: np.ndarray, gate_m: float = 0.5, min_inliers: int = 6) -> None:
        from scipy.spatial import cKDTree

        self.xy = np.asarray(catalog_xy)
        self.tree = cKDTree(self.xy)
        self.gate_m = gate_m
        self.min_inliers = min_inliers

    def match(self, local_xy: np.ndarray, local_size: np.ndarray, prior=None):
        R, tr = np.eye(2), np.zeros(2)
        pairs = np.zeros((0, 2), int)
        for _ in range(5):
            moved = local_xy @ R.T + tr
            d, j = self.tree.query(moved)
            ok = d < self.gate_m
            if ok.sum() < self.min_inliers:
                return None
            pairs = np.column_stack([np.flatnonzero(ok), j[ok]])
            src, dst = local_xy[pairs[:, 0]], self.xy[pairs[:, 1]]
            ms, md = src.mean(0), dst.mean(0)
            U, _, Vt = np.linalg.svd((src - ms).T @ (dst - md))
            D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
            R = Vt.T @ D @ U.T
            tr = md - R @ ms
        res = local_xy[pairs[:, 0]] @ R.T + tr - self.xy[pairs[:, 1]]
        return _Match(float(np.arctan2(R[1, 0], R[0, 0])), tr, 1.0, pairs, float(np.sqrt(np.mean(np.sum(res**2, 1)))))


def write_input_dir(path, inputs: RunInputs):
    """``inputs`` written as a complete `fgslam sim`-like directory (bag/, catalog.csv, manifest),
    the input of `fgslam run DIR` and `fgslam compare`; returns ``path``."""
    from fgslam.io.catalog_csv import write_catalog_csv
    from fgslam.io.outdir import OutputDir
    from sim.bag_writer import write_bag

    with OutputDir(path, "sim") as od:
        write_bag(od.staging / "bag", inputs.measurements)
        write_catalog_csv(od.staging / "catalog.csv", inputs.catalog)
        od.commit()
    return path
