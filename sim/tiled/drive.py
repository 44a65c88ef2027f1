"""The rover's drive over a tiled world, one step at a time: strategic legs, local plans, the
pure-pursuit controller of :mod:`sim.rover` on each drive step, stops between them. Yields
:class:`DriveSegment` s (the planar path of one step or stop and the terrain under it), so no
whole-traverse array is ever built."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from sim.config import SimConfig
from sim.errors import SimError
from sim.rover import PlanarPath, drive_route
from sim.terrain import Heightmap
from sim.tiled.route import LocalPlanner, clip_length, plan_strategic
from sim.tiled.world import TiledWorld

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriveSegment:
    """One drive step or stop: ``path`` (its ticks; none repeats the previous segment's last),
    ``terrain`` (a DEM under it), ``kind`` ("start", "drive", "stop")."""

    path: PlanarPath
    terrain: Heightmap
    kind: str


def _standstill(x: float, y: float, yaw: float, n: int, dt: float) -> PlanarPath:
    return PlanarPath(dt, np.full(n, x), np.full(n, y), np.full(n, yaw), np.zeros(0, dtype=int))


class Driver:
    """Drives ``cfg.traverse.distance_m`` over ``world`` (see the module doc); :attr:`route` holds
    the strategic waypoints, the counters the progress."""

    def __init__(self, world: TiledWorld, cfg: SimConfig, rng: np.random.Generator) -> None:
        self.world, self.cfg = world, cfg
        rc = cfg.tiled.route
        # a loop's polygon is a little shorter than the traverse (local detours add length): the
        # drive ends back at the start; otherwise plenty of route for the detours
        length = cfg.traverse.distance_m / 1.05 if rc.loop else 1.3 * cfg.traverse.distance_m + 2 * rc.strategic_max_m
        self.route = plan_strategic(world, length, rc, rng)
        self.planner = LocalPlanner(world, rc, speed_mps=cfg.rover.cruise_speed_mps)
        self.odometer_m = 0.0
        self.n_steps = 0
        self.n_stops = 0
        self.legs_done = 0
        self.ticks = 0  # ticks yielded so far

    def _dem_around(self, xy: np.ndarray, margin_m: float = 3.0) -> Heightmap:
        xy = np.reshape(xy, (-1, 2))
        return self.world.heightmap((xy[:, 0].min() - margin_m, xy[:, 0].max() + margin_m,
                                     xy[:, 1].min() - margin_m, xy[:, 1].max() + margin_m))

    def _ground_length(self, path: PlanarPath, dem: Heightmap) -> float:
        xy = np.column_stack([path.x_m, path.y_m])
        z = dem.height_at(xy)
        return float(np.sum(np.sqrt(np.sum(np.diff(xy, axis=0) ** 2, axis=1) + np.diff(z) ** 2)))

    def segments(self) -> Iterator[DriveSegment]:
        cfg, rc = self.cfg, self.cfg.tiled.route
        dt = 1.0 / cfg.sensors.imu.rate_hz
        pos = self.route[0].copy()
        d0 = self.route[1] - self.route[0]
        yaw = math.atan2(d0[1], d0[0])
        n0 = max(round(cfg.traverse.start_pause_s / dt), 1)
        self.ticks = n0
        yield DriveSegment(_standstill(pos[0], pos[1], yaw, n0, dt), self._dem_around(pos), "start")
        leg, stuck = 0, 0
        total = cfg.traverse.distance_m
        while self.odometer_m < total - 0.05:
            if leg + 1 >= len(self.route):
                if rc.loop:
                    break  # back at the start
                raise SimError(f"strategic route of world {self.world.name} ended after {self.odometer_m:.0f} m")
            a, b = self.route[leg], self.route[leg + 1]
            L = float(np.linalg.norm(b - a))
            u = (b - a) / max(L, 1e-9)
            s = float(np.clip((pos - a) @ u, 0.0, L))
            if L - s < 3.0 or np.linalg.norm(pos - b) < 3.0:  # at the waypoint: next leg (and the stop)
                leg += 1
                self.legs_done += 1
                if rc.stop_s > 0:
                    self.n_stops += 1
                    n = round(rc.stop_s / dt)
                    self.ticks += n
                    yield DriveSegment(_standstill(pos[0], pos[1], yaw, n, dt), self._dem_around(pos), "stop")
                continue
            goal = a + min(s + self.planner.horizon_m, L) * u
            near_end = rc.loop and leg == len(self.route) - 2
            whole = min(s + self.planner.horizon_m, L) >= L and L - s < rc.drive_step_m + 5  # the leg's last step
            plan = self.planner.plan(pos, goal, near_end_of_loop=near_end, check_m=math.inf if whole else rc.drive_step_m)
            step = plan if whole else clip_length(plan, rc.drive_step_m)
            dem = self._dem_around(step)
            path = drive_route(dem, step, total - self.odometer_m, cfg.rover.cruise_speed_mps, cfg.rover, dt,
                               yaw0_rad=yaw, stop_at_end=True)
            moved = self._ground_length(path, dem)
            stuck = stuck + 1 if moved < 0.05 else 0
            if stuck >= 5:
                raise SimError(f"rover stuck at ({pos[0]:.1f}, {pos[1]:.1f}) in world {self.world.name}")
            self.odometer_m += moved
            self.n_steps += 1
            xy = np.column_stack([path.x_m, path.y_m])
            self.planner.record(xy, dt * (self.ticks - 1 + np.arange(len(xy))))
            pos, yaw = xy[-1].copy(), float(path.yaw_rad[-1])
            tail = PlanarPath(dt, path.x_m[1:], path.y_m[1:], path.yaw_rad[1:], np.zeros(0, dtype=int))
            if len(tail.x_m):
                self.ticks += len(tail.x_m)
                yield DriveSegment(tail, dem, "drive")
