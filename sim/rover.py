"""The JPL Open Source Rover as a planar-kinematics body on the terrain.

A pure-pursuit controller drives the rover along the waypoint route on its true pose (the way a
simulator's navigation stack does); heading errors above ``turn_in_place_deg`` make it stop and
turn in place. Pauses at those stops stretch the run to the requested duration. The 3D pose then
follows the terrain: a plane through the four corner-wheel contact heights gives z, roll and pitch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.config import RoverConfig
from sim.errors import SimError
from sim.terrain import Heightmap


@dataclass(frozen=True)
class PlanarPath:
    """Horizontal rover path sampled every ``dt_s``: ``x_m``, ``y_m``, ``yaw_rad`` (K,), and the
    ticks at which the rover stood still before turning in place (``stop_ticks``)."""

    dt_s: float
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    stop_ticks: np.ndarray


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class _SurfaceProbe:
    """Scalar bilinear height and gradient of a heightmap (fast inside the controller loop)."""

    def __init__(self, terrain: Heightmap) -> None:
        self.z = terrain.z_m.tolist()
        self.x0, _, self.y0, _ = terrain.extent
        self.dx, self.dy = terrain.spacing_m
        self.nyx = (terrain.z_m.shape[0] - 1, terrain.z_m.shape[1] - 1)

    def __call__(self, x: float, y: float) -> tuple[float, float, float]:
        fx = min(max((x - self.x0) / self.dx, 0.0), self.nyx[1] - 1e-6)
        fy = min(max((y - self.y0) / self.dy, 0.0), self.nyx[0] - 1e-6)
        j, i = int(fx), int(fy)
        u, v = fx - j, fy - i
        r0, r1 = self.z[i], self.z[i + 1]
        z00, z01, z10, z11 = r0[j], r0[j + 1], r1[j], r1[j + 1]
        z = z00 * (1 - u) * (1 - v) + z01 * u * (1 - v) + z10 * (1 - u) * v + z11 * u * v
        gx = ((z01 - z00) * (1 - v) + (z11 - z10) * v) / self.dx
        gy = ((z10 - z00) * (1 - u) + (z11 - z01) * u) / self.dy
        return z, gx, gy


def drive_route(
    terrain: Heightmap, waypoints: np.ndarray, distance_m: float, v_cruise_mps: float, cfg: RoverConfig, dt_s: float,
    *, yaw0_rad: float | None = None, stop_at_end: bool = False,
) -> PlanarPath:
    """Run the pure-pursuit controller on ``waypoints`` (W, 2) until ``distance_m`` (3D, along the
    ground) has been driven; returns the planar path at ``dt_s``. The rover starts at rest at the
    first waypoint, heading ``yaw0_rad`` (default: along the first segment). ``stop_at_end``: a
    drive step: brake to a stop at the route's end (or after ``distance_m``, whichever is first)."""
    wp = np.asarray(waypoints, dtype=float)
    if len(wp) < 2:
        raise SimError("a route needs at least two waypoints")
    seg = np.diff(wp, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    s_wp = np.concatenate([[0.0], np.cumsum(seg_len)])
    wpl, segl, lenl, swl = wp.tolist(), seg.tolist(), seg_len.tolist(), s_wp.tolist()
    n_seg = len(segl)
    probe = _SurfaceProbe(terrain)

    def point_at(s: float) -> tuple[float, float]:
        s = min(max(s, 0.0), swl[-1])
        i = min(int(np.searchsorted(s_wp, s, side="right")) - 1, n_seg - 1)
        f = (s - swl[i]) / max(lenl[i], 1e-12)
        return wpl[i][0] + segl[i][0] * f, wpl[i][1] + segl[i][1] * f

    x, y = wpl[0]
    yaw = math.atan2(segl[0][1], segl[0][0]) if yaw0_rad is None else _wrap(float(yaw0_rad))
    v = w = 0.0
    odo = 0.0
    z_prev = probe(x, y)[0]
    i_seg, s_proj = 0, 0.0
    turning = stop_recorded = False
    turn_on, turn_off = math.radians(cfg.turn_in_place_deg), math.radians(cfg.turn_done_deg)
    dv, dw = cfg.accel_mps2 * dt_s, cfg.yaw_accel_radps2 * dt_s
    stops: list[int] = []
    xs, ys, yaws = [x], [y], [yaw]
    max_ticks = int(50 * distance_m / max(v_cruise_mps, 1e-3) / dt_s) + 10000
    for tick in range(1, max_ticks):
        # project onto the nearby segments, only moving forward along the route
        best_d2, best_s = math.inf, s_proj
        for j in range(i_seg, min(i_seg + 2, n_seg)):  # never skip a segment of a route that doubles back
            (ax, ay), (sx, sy), L = wpl[j], segl[j], lenl[j]
            u = min(max(((x - ax) * sx + (y - ay) * sy) / max(L * L, 1e-12), 0.0), 1.0)
            d2 = (ax + u * sx - x) ** 2 + (ay + u * sy - y) ** 2
            if d2 < best_d2 - 1e-9:
                best_d2, best_s, i_best = d2, swl[j] + u * L, j
        i_seg = i_best
        s_proj = max(s_proj, best_s)
        tx, ty = point_at(s_proj + cfg.lookahead_m)
        alpha = _wrap(math.atan2(ty - y, tx - x) - yaw)
        remaining = distance_m - odo
        if stop_at_end:
            remaining = min(remaining, swl[-1] - s_proj)
        if not turning and abs(alpha) > turn_on:
            turning, stop_recorded = True, False
        if turning:
            v_des, w_des = 0.0, 0.0
            if v == 0.0:
                if not stop_recorded:
                    stops.append(tick - 1)
                    stop_recorded = True
                w_des = math.copysign(min(cfg.turn_yaw_rate_radps, math.sqrt(2 * cfg.yaw_accel_radps2 * abs(alpha))), alpha)
            if abs(alpha) < turn_off:
                turning, w_des = False, 0.0
        else:
            v_des = min(v_cruise_mps, math.sqrt(max(2 * cfg.accel_mps2 * remaining, 0.0)))
            w_des = 2 * max(v, 0.02) * math.sin(alpha) / cfg.lookahead_m
            w_des = min(max(w_des, -cfg.max_yaw_rate_radps), cfg.max_yaw_rate_radps)
        v += min(max(v_des - v, -dv), dv)
        w += min(max(w_des - w, -dw), dw)
        # v is the speed along the ground: the horizontal step shrinks on slopes
        _, gx, gy = probe(x, y)
        slope_along = gx * math.cos(yaw) + gy * math.sin(yaw)
        step_h = v * dt_s / math.sqrt(1.0 + slope_along**2)
        yaw_mid = yaw + 0.5 * w * dt_s
        x += step_h * math.cos(yaw_mid)
        y += step_h * math.sin(yaw_mid)
        yaw = _wrap(yaw + w * dt_s)
        z = probe(x, y)[0]
        odo += math.hypot(step_h, z - z_prev)
        z_prev = z
        xs.append(x)
        ys.append(y)
        yaws.append(yaw)
        if remaining <= 1e-3 or (remaining < 0.05 and v < 1e-3 and not turning):
            break
        if not stop_at_end and s_proj >= swl[-1] - 1e-6 and not turning and v < 1e-4 and tick > 10:
            raise SimError(f"route of {swl[-1]:.1f} m ended before the traverse of {distance_m:.1f} m")
    else:
        raise SimError(f"rover did not finish a {distance_m:.1f} m traverse in {max_ticks} ticks")
    return PlanarPath(dt_s, np.array(xs), np.array(ys), np.unwrap(np.array(yaws)), np.array(stops, dtype=int))


def insert_pauses(path: PlanarPath, n_ticks: int, start_pause_ticks: int) -> PlanarPath:
    """Stretch ``path`` by ``start_pause_ticks`` still ticks at the start plus ``n_ticks`` more spread
    evenly over its stops (the end when it has none)."""
    where = list(path.stop_ticks) if len(path.stop_ticks) else [len(path.x_m) - 1]
    per = np.full(len(where), max(n_ticks, 0) // len(where))
    per[: max(n_ticks, 0) % len(where)] += 1
    idx = [np.zeros(start_pause_ticks, dtype=int)]
    prev = 0
    new_stops = []
    count = start_pause_ticks
    for k, extra in zip(where, per):
        idx.append(np.arange(prev, k + 1))
        count += k + 1 - prev
        new_stops.append(count - 1)
        idx.append(np.full(extra, k))
        count += extra
        prev = k + 1
    idx.append(np.arange(prev, len(path.x_m)))
    sel = np.concatenate(idx)
    return PlanarPath(path.dt_s, path.x_m[sel], path.y_m[sel], path.yaw_rad[sel], np.array(new_stops, dtype=int))


def terrain_poses(terrain: Heightmap, path: PlanarPath, cfg: RoverConfig) -> np.ndarray:
    """T_world_base (K, 4, 4) of the rover on the terrain: plane through the corner-wheel contacts."""
    c, s = np.cos(path.yaw_rad), np.sin(path.yaw_rad)
    hw, ht = cfg.wheelbase_m / 2, cfg.track_m / 2
    z = {}
    for name, (u, v) in {"fl": (hw, ht), "fr": (hw, -ht), "rl": (-hw, ht), "rr": (-hw, -ht)}.items():
        z[name] = terrain.height_at(np.column_stack([path.x_m + u * c - v * s, path.y_m + u * s + v * c]))
    z0 = 0.25 * (z["fl"] + z["fr"] + z["rl"] + z["rr"])
    sx = 0.5 * ((z["fl"] + z["fr"]) - (z["rl"] + z["rr"])) / cfg.wheelbase_m
    sy = 0.5 * ((z["fl"] + z["rl"]) - (z["fr"] + z["rr"])) / cfg.track_m
    zeros = np.zeros_like(c)
    tu = np.column_stack([c, s, sx])
    tv = np.column_stack([-s, c, sy])
    xb = tu / np.linalg.norm(tu, axis=1, keepdims=True)
    n = np.cross(tu, tv)
    zb = n / np.linalg.norm(n, axis=1, keepdims=True)
    yb = np.cross(zb, xb)
    T = np.zeros((len(c), 4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = xb, yb, zb
    T[:, :3, 3] = np.column_stack([path.x_m, path.y_m, z0]) + cfg.base_height_m * zb
    T[:, 3, 3] = 1.0 + zeros
    return T
