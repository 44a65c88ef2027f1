"""Mission-like routes over a tiled world.

Strategic: waypoints ``strategic_min_m``-``strategic_max_m`` apart, the heading changing by a
normal draw (sigma ``heading_sigma_deg``, at most ``max_turn_deg``) at each; a leg is accepted when it
stays ``edge_margin_m`` inside the world, ``path_clearance_m`` from every earlier leg but the last,
outside the interior of every crater of 30 m and more (plus clearance), and below
``max_slope_deg`` on the coarse DEM. With ``loop`` the waypoints go round a closed polygon back to
the start.

Local (:class:`LocalPlanner`): the rover plans on a ``cell_m`` grid around the next stretch of its
leg (``corridor_m`` either side), avoiding rocks of ``avoid_rock_diameter_m`` and more, crater
interiors deeper than ``avoid_crater_depth_m``, slopes above ``max_slope_deg`` and every place
within ``revisit_radius_m`` of where it has been and already left (so it never comes back), by
Dijkstra on the 8-connected grid (scipy.sparse.csgraph) and line-of-sight smoothing; it drives
``drive_step_m`` of the plan, stops, and plans again.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from sim.craters import depth_ratio
from sim.errors import SimError
from sim.tiled.config import KmRouteConfig
from sim.tiled.world import TiledWorld

log = logging.getLogger(__name__)

STRATEGIC_CRATER_M = 30.0  # craters this big are avoided by the strategic legs


def _seg_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (N,) of points ``p`` (N, 2) to segment a-b."""
    ab = b - a
    u = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(a + u[:, None] * ab - p, axis=1)


def _leg_ok(world: TiledWorld, pts: list[np.ndarray], q: np.ndarray, cfg: KmRouteConfig) -> bool:
    a = pts[-1]
    xmin, xmax, ymin, ymax = world.extent
    m = cfg.edge_margin_m
    if not (xmin + m <= q[0] <= xmax - m and ymin + m <= q[1] <= ymax - m):
        return False
    n = max(int(np.linalg.norm(q - a) / 4.0), 2)
    samples = a + np.linspace(0.0, 1.0, n)[:, None] * (q - a)
    for k in range(len(pts) - 2):  # every earlier leg but the one ending at a
        if _seg_dist(samples, pts[k], pts[k + 1]).min() < cfg.path_clearance_m:
            return False
    box = (min(a[0], q[0]), max(a[0], q[0]), min(a[1], q[1]), max(a[1], q[1]))
    big = world.craters_near(box, reach_radii=1.5, d_min_m=STRATEGIC_CRATER_M)
    if len(big) and np.any(_seg_dist(big.xy_m, a, q) < 0.5 * big.diameter_m * 1.3 + 5.0):
        return False
    dem = world.coarse_heightmap((box[0] - 16, box[1] + 16, box[2] - 16, box[3] + 16))
    grad = dem.gradient_at(samples)
    return bool(np.degrees(np.arctan(np.hypot(grad[:, 0], grad[:, 1]).max())) <= cfg.max_slope_deg)


def plan_strategic(world: TiledWorld, length_m: float, cfg: KmRouteConfig, rng: np.random.Generator) -> np.ndarray:
    """Strategic waypoints (W, 2), polyline length >= ``length_m``; the first is the start."""
    xmin, xmax, ymin, ymax = world.extent
    centre = np.array([0.5 * (xmin + xmax), 0.5 * (ymin + ymax)])
    side = min(xmax - xmin, ymax - ymin)
    if cfg.loop:
        return _loop_route(world, centre, length_m, cfg, rng)
    for _restart in range(20):
        pts = [_free_start(world, centre, side, cfg, rng)]
        heading = rng.uniform(-np.pi, np.pi)
        total = 0.0
        while total < length_m:
            chosen = None
            for attempt in range(120):
                spread = math.radians(cfg.heading_sigma_deg) * (1.0 + attempt / 30.0)
                turn = float(np.clip(spread * rng.standard_normal(), -math.radians(cfg.max_turn_deg), math.radians(cfg.max_turn_deg)))
                if len(pts) == 1:
                    turn = rng.uniform(-np.pi, np.pi)
                h = heading + turn
                q = pts[-1] + rng.uniform(cfg.strategic_min_m, cfg.strategic_max_m) * np.array([np.cos(h), np.sin(h)])
                if _leg_ok(world, pts, q, cfg):
                    chosen, heading = q, h
                    break
            if chosen is None:
                break
            total += float(np.linalg.norm(chosen - pts[-1]))
            pts.append(chosen)
        if total >= length_m:
            return np.array(pts)
    raise SimError(f"no strategic route of {length_m:.0f} m fits world {world.name} ({side:.0f} m side) "
                   f"without coming back near itself; use a bigger tiled.size_m")


def _free_start(world: TiledWorld, centre: np.ndarray, side: float, cfg: KmRouteConfig, rng: np.random.Generator) -> np.ndarray:
    """A start in the central part of the world on open, gentle ground: clear of crater interiors
    the rover avoids (by 5 m), of big rocks and of slopes above the limit."""
    for _ in range(200):
        p = centre + (rng.random(2) - 0.5) * 0.3 * side
        box = (p[0] - 12.0, p[0] + 12.0, p[1] - 12.0, p[1] + 12.0)
        cr = world.craters_near(box, reach_radii=1.0)
        deep = cr.diameter_m * depth_ratio(cr.degradation) > cfg.avoid_crater_depth_m
        if np.any(np.linalg.norm(cr.xy_m[deep] - p, axis=1) < 0.5 * cr.diameter_m[deep] + 5.0):
            continue
        rocks = world.rocks_in(box, cfg.avoid_rock_diameter_m)
        if np.any(np.linalg.norm(rocks.xy_m - p, axis=1) < 0.5 * rocks.diameter_m + 1.5):
            continue
        hm = world.heightmap(box)
        g = hm.gradient_at(p[None] + np.array([[dx, dy] for dx in (-4, 0, 4) for dy in (-4, 0, 4)]))
        if np.degrees(np.arctan(np.hypot(g[:, 0], g[:, 1]).max())) < cfg.max_slope_deg:
            return p
    raise SimError(f"no open ground to start on near the centre of world {world.name}")


def _loop_route(world: TiledWorld, centre: np.ndarray, length_m: float, cfg: KmRouteConfig,
                rng: np.random.Generator) -> np.ndarray:
    """A closed polygon of perimeter ~``length_m`` from a free start near the world centre back to it."""
    xmin, xmax, ymin, ymax = world.extent
    start = _free_start(world, centre, min(xmax - xmin, ymax - ymin), cfg, rng)
    r = length_m / (2.0 * np.pi) * 1.02
    n = max(int(length_m / 200.0), 6)
    th = np.linspace(0.0, 2.0 * np.pi, n + 1) + rng.uniform(0, 2 * np.pi)
    rad = r * (1.0 + 0.1 * rng.standard_normal(n + 1))
    rad[-1] = rad[0]
    ring = np.column_stack([rad * np.cos(th), rad * np.sin(th)])
    pts = start - ring[0] + ring
    if pts[:, 0].min() < xmin or pts[:, 0].max() > xmax or pts[:, 1].min() < ymin or pts[:, 1].max() > ymax:
        raise SimError(f"a loop of {length_m:.0f} m does not fit world {world.name}")
    return pts


class LocalPlanner:
    """Grid planner of the local stretch of a leg (see the module doc)."""

    def __init__(self, world: TiledWorld, cfg: KmRouteConfig, horizon_m: float = 50.0, speed_mps: float = 0.12) -> None:
        self.world, self.cfg, self.horizon_m, self.speed_mps = world, cfg, horizon_m, speed_mps
        self.history_xy: list[tuple[float, float]] = []  # the driven path, every ~metre
        self.history_t: list[float] = []  # and when the rover was there (s from the start)
        self.n_relaxed = 0  # plans that had to let the rover near its old path

    def record(self, xy: np.ndarray, t_s: np.ndarray) -> None:
        """Append the driven positions ``xy`` (N, 2) at times ``t_s`` (N,) to the history (~1 m apart)."""
        for p, t in zip(np.reshape(xy, (-1, 2)), np.ravel(t_s)):
            if not self.history_xy or math.dist(self.history_xy[-1], p) >= 1.0:
                self.history_xy.append((float(p[0]), float(p[1])))
                self.history_t.append(float(t))

    def plan(self, start: np.ndarray, goal: np.ndarray, *, near_end_of_loop: bool = False,
             check_m: float = math.inf) -> np.ndarray:
        """Polyline (M, 2) from ``start`` towards ``goal``. Where the goal cannot be reached, or the
        first ``check_m`` of the plan would bring the rover back near a place it left more than
        ``revisit_after_s`` ago (a path that curls round past the places still open when it was
        planned), goals turned by up to 120 deg about the rover are tried, then the reachable cell
        nearest the goal; only when the old path walls the rover in is the revisit rule dropped
        (counted)."""
        use_history = not near_end_of_loop
        best = None
        d = goal - start
        for turn in (0.0, 30.0, -30.0, 60.0, -60.0, 90.0, -90.0, 120.0, -120.0):
            c, s_ = math.cos(math.radians(turn)), math.sin(math.radians(turn))
            g = start + np.array([c * d[0] - s_ * d[1], s_ * d[0] + c * d[1]])
            found = self._plan_to(start, g, use_history)
            if found is None:
                continue
            path, reached = found
            if use_history and self.comes_back(clip_length(path, check_m)):
                continue
            if reached:
                return path
            if best is None:
                best = path  # the partial plan towards the leg's own goal first
        if best is not None:
            return best
        self.n_relaxed += 1
        log.warning("local plan at (%.1f, %.1f): no way on that keeps clear of the old path", *start)
        found = self._plan_to(start, goal, use_history=False)
        if found is None:
            raise SimError(f"local planner: no free path from ({start[0]:.1f}, {start[1]:.1f}) in world {self.world.name}")
        return found[0]

    def comes_back(self, plan_xy: np.ndarray) -> bool:
        """Would driving ``plan_xy`` (M, 2) (at ``speed_mps``) after the recorded history count as
        coming back (:func:`revisits`, the same radii)?"""
        if len(self.history_xy) < 2 or len(plan_xy) < 2:
            return False
        cfg = self.cfg
        r, r_left = cfg.revisit_radius_m, cfg.revisit_radius_m + 1.0
        seg = np.linalg.norm(np.diff(plan_xy, axis=0), axis=1)
        n = np.maximum(np.ceil(seg).astype(int), 1)
        dense = np.vstack([plan_xy[k] + np.linspace(0, 1, n[k], endpoint=False)[:, None] * (plan_xy[k + 1] - plan_xy[k])
                           for k in range(len(seg))] + [plan_xy[-1:]])
        h, th = np.array(self.history_xy), np.array(self.history_t)
        t_plan_end = th[-1] + float(seg.sum()) / max(self.speed_mps, 1e-3)
        near, _ = cKDTree(dense).query(h, distance_upper_bound=r)
        cand = np.flatnonzero(np.isfinite(near) & (t_plan_end - th > cfg.revisit_after_s))
        for i in cand:
            seq = np.vstack([h[i + 1:], dense])
            dist = np.linalg.norm(seq - h[i], axis=1)
            out = np.flatnonzero(dist > r_left)
            if len(out) and np.any(dist[max(out[0], len(h) - i - 1):] < r):
                return True
        return False

    def _plan_to(self, start: np.ndarray, goal: np.ndarray, use_history: bool):
        c = self.cfg.corridor_m
        ext = (min(start[0], goal[0]) - c, max(start[0], goal[0]) + c, min(start[1], goal[1]) - c, max(start[1], goal[1]) + c)
        blocked, cost, x0, y0 = self._costmap(ext, start, use_history)
        return self._search(blocked, cost, x0, y0, start, goal)

    def _costmap(self, ext, start, use_history: bool):
        cfg, res = self.cfg, self.cfg.cell_m
        hm = self.world.heightmap(ext)
        xs = np.arange(ext[0], ext[1] + 1e-9, res)
        ys = np.arange(ext[2], ext[3] + 1e-9, res)
        gx, gy = np.meshgrid(xs, ys)
        pts = np.column_stack([gx.ravel(), gy.ravel()])
        grad = hm.gradient_at(pts)
        slope = np.degrees(np.arctan(np.hypot(grad[:, 0], grad[:, 1]))).reshape(gx.shape)
        blocked = slope > cfg.max_slope_deg
        rocks = self.world.rocks_in((ext[0] - 2, ext[1] + 2, ext[2] - 2, ext[3] + 2), cfg.avoid_rock_diameter_m)
        discs = [(rocks.xy_m, 0.5 * rocks.diameter_m + cfg.rock_clearance_m)]
        cr = self.world.craters_near(ext, reach_radii=1.2)
        deep = cr.diameter_m * depth_ratio(cr.degradation) > cfg.avoid_crater_depth_m
        discs.append((cr.xy_m[deep], 0.5 * cr.diameter_m[deep] + cfg.crater_clearance_m))
        for centres, radii in discs:
            _mark_discs(blocked, centres, radii, ext[0], ext[2], res)
        if use_history and self.history_xy:
            h = np.array(self.history_xy)
            # places it has left (more than radius + 1 m away) are closed to radius + 0.5 m: the
            # rover itself always stays outside what is closed
            r = cfg.revisit_radius_m
            h = h[np.linalg.norm(h - start, axis=1) >= r + 1.0]
            inside = (h[:, 0] > ext[0] - r) & (h[:, 0] < ext[1] + r) & (h[:, 1] > ext[2] - r) & (h[:, 1] < ext[3] + r)
            _mark_discs(blocked, h[inside], np.full(int(inside.sum()), r + 0.5), ext[0], ext[2], res)
        # the rover's own cell and its immediate surroundings stay usable (it is standing there)
        _mark_discs(blocked, np.reshape(start, (1, 2)), np.array([0.8]), ext[0], ext[2], res, value=False)
        cost = 1.0 + 2.0 * (np.clip(slope / cfg.max_slope_deg, 0, 1)) ** 2
        # stay a little off obstacles where there is room
        dist = distance_transform_edt(~blocked) * res
        cost = cost + 1.5 * np.exp(-dist / 0.5)
        return blocked, cost, ext[0], ext[2]

    def _search(self, blocked, cost, x0, y0, start, goal):
        res = self.cfg.cell_m
        ny, nx = blocked.shape
        def cell(p):
            return (int(np.clip(round((p[1] - y0) / res), 0, ny - 1)), int(np.clip(round((p[0] - x0) / res), 0, nx - 1)))
        s = cell(start)
        free = ~blocked
        idx = np.arange(ny * nx).reshape(ny, nx)
        rows, cols, w = [], [], []
        for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = idx[max(0, -di):ny - max(0, di), max(0, -dj):nx - max(0, dj)]
            b = idx[max(0, di):ny - max(0, -di) if di <= 0 else ny, max(0, dj):nx - max(0, -dj) if dj <= 0 else nx]
            a, b = a.ravel(), b.ravel()
            ok = free.ravel()[a] & free.ravel()[b]
            a, b = a[ok], b[ok]
            step = res * math.hypot(di, dj)
            wt = step * 0.5 * (cost.ravel()[a] + cost.ravel()[b])
            rows += [a, b]
            cols += [b, a]
            w += [wt, wt]
        g = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(ny * nx, ny * nx)).tocsr()
        dist, pred = dijkstra(g, indices=idx[s], return_predecessors=True)
        reach = np.isfinite(dist)
        if reach.sum() < 2:
            return None
        gi, gj = cell(goal)
        target = idx[gi, gj]
        reached = bool(reach[target])
        if not reached:  # the reachable cell nearest the goal
            ii, jj = np.divmod(np.flatnonzero(reach), nx)
            k = int(np.argmin((ii - gi) ** 2 + (jj - gj) ** 2))
            target = int(ii[k] * nx + jj[k])
            if math.hypot(ii[k] - s[0], jj[k] - s[1]) * res < 2.0:
                return None
        chain = [target]
        while chain[-1] != idx[s]:
            chain.append(int(pred[chain[-1]]))
        chain = np.array(chain[::-1])
        ci, cj = np.divmod(chain, nx)
        xy = np.column_stack([x0 + cj * res, y0 + ci * res])
        xy[0] = start
        return _smooth(xy, blocked, x0, y0, res), reached


def clip_length(poly: np.ndarray, length_m: float) -> np.ndarray:
    """The first ``length_m`` of polyline ``poly`` (M, 2) (whole when shorter)."""
    if not math.isfinite(length_m):
        return poly
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= length_m:
        return poly
    k = int(np.searchsorted(s, length_m))
    f = (length_m - s[k - 1]) / max(seg[k - 1], 1e-12)
    return np.vstack([poly[:k], poly[k - 1] + f * (poly[k] - poly[k - 1])])


def _mark_discs(grid: np.ndarray, centres: np.ndarray, radii: np.ndarray, x0: float, y0: float, res: float,
                value: bool = True) -> None:
    """Set the cells of ``grid`` (ny, nx) within ``radii`` (K,) of ``centres`` (K, 2) to ``value``."""
    ny, nx = grid.shape
    for (cx, cy), r in zip(np.reshape(centres, (-1, 2)), np.ravel(radii)):
        j0, j1 = max(int((cx - r - x0) / res), 0), min(math.ceil((cx + r - x0) / res), nx - 1)
        i0, i1 = max(int((cy - r - y0) / res), 0), min(math.ceil((cy + r - y0) / res), ny - 1)
        if j1 < j0 or i1 < i0:
            continue
        jj = x0 + res * np.arange(j0, j1 + 1) - cx
        ii = y0 + res * np.arange(i0, i1 + 1) - cy
        m = ii[:, None] ** 2 + jj[None, :] ** 2 <= r * r
        sub = grid[i0:i1 + 1, j0:j1 + 1]
        sub[m] = value


def _smooth(xy: np.ndarray, blocked: np.ndarray, x0: float, y0: float, res: float) -> np.ndarray:
    """Line-of-sight shortcuts of a grid path (N, 2): keep a vertex only where the straight line
    to the next kept one would cross a blocked cell."""
    ny, nx = blocked.shape

    def clear(a, b):
        n = max(int(np.linalg.norm(b - a) / (0.5 * res)), 2)
        p = a + np.linspace(0, 1, n)[:, None] * (b - a)
        j = np.clip(np.rint((p[:, 0] - x0) / res).astype(int), 0, nx - 1)
        i = np.clip(np.rint((p[:, 1] - y0) / res).astype(int), 0, ny - 1)
        return not blocked[i[1:], j[1:]].any()

    out = [xy[0]]
    k = 0
    while k < len(xy) - 1:
        j = k + 1
        while j + 1 < len(xy) and clear(xy[k], xy[j + 1]):  # walk on while the line of sight holds
            j += 1
        out.append(xy[j])
        k = j
    return np.array(out)


def revisits(t_s: np.ndarray, xy_m: np.ndarray, radius_m: float = 20.0, after_s: float = 300.0,
             leave_margin_m: float = 1.0) -> int:
    """How many places the rover came back to: path points (N, 2) at times (N,) (at most ~1 m
    apart) from which it later moved more than ``radius_m + leave_margin_m`` away (it left) and
    then, more than ``after_s`` after being there, came back within ``radius_m``."""
    xy = np.reshape(np.asarray(xy_m, dtype=float), (-1, 2))
    t = np.ravel(t_s)
    if len(xy) < 2:
        return 0
    tree = cKDTree(xy)
    n_back = 0
    for i, (near, wide) in enumerate(zip(tree.query_ball_point(xy, radius_m),
                                         tree.query_ball_point(xy, radius_m + leave_margin_m))):
        wide = np.sort(np.asarray(wide))
        later = wide[wide > i]
        # the points after i stay in the wider ball up to the first index missing from it
        run = later - np.arange(i + 1, i + 1 + len(later))
        left_at = i + 1 + int(np.argmax(run != 0)) if np.any(run != 0) else len(xy)
        near = np.asarray(near)
        back = near[(near > left_at) & (t[near] - t[i] > after_s)]
        n_back += bool(len(back))
    return n_back
