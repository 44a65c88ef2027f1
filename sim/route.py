"""Seeded waypoint routes: a persistent random walk inside the world that keeps away from its
edges and from big rocks."""

from __future__ import annotations

import numpy as np

from sim.config import TraverseConfig
from sim.world import World


def _segment_clear(a: np.ndarray, b: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> bool:
    """True when segment a-b (2,) passes no obstacle circle (centres (K, 2), radii (K,))."""
    if len(centres) == 0:
        return True
    ab = b - a
    u = np.clip(((centres - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    d = np.linalg.norm(a + u[:, None] * ab - centres, axis=1)
    return bool(np.all(d > radii))


def plan_route(world: World, length_m: float, cfg: TraverseConfig, rng: np.random.Generator) -> np.ndarray:
    """Waypoints (W, 2) in world metres, polyline length >= ``length_m``; the first is the start."""
    big = world.rocks.size_m >= cfg.avoid_rock_diameter_m
    centres = world.rocks.xyz_m[big, :2]
    radii = world.rocks.size_m[big] / 2 + cfg.rock_clearance_m
    xmin, xmax, ymin, ymax = world.extent
    margin = min(cfg.edge_margin_m, 0.25 * (xmax - xmin), 0.25 * (ymax - ymin))
    lo = np.array([xmin + margin, ymin + margin])
    hi = np.array([xmax - margin, ymax - margin])

    def free(p: np.ndarray) -> bool:
        return bool(np.all(p >= lo) and np.all(p <= hi)) and bool(
            len(centres) == 0 or np.min(np.linalg.norm(centres - p, axis=1) - radii) > 0
        )

    start = None
    for _ in range(1000):
        cand = lo + (hi - lo) * (0.25 + 0.5 * rng.random(2))  # start in the central part
        if free(cand):
            start = cand
            break
    if start is None:
        start = 0.5 * (lo + hi)
    pts = [start]
    heading = rng.uniform(-np.pi, np.pi)
    total = 0.0
    while total < length_m:
        p = pts[-1]
        chosen = None
        for attempt in range(60):
            spread = np.deg2rad(cfg.heading_sigma_deg) * (1.0 + attempt / 15.0)
            h = heading + spread * rng.standard_normal()
            if attempt >= 40:  # boxed in: head for the middle of the world
                h = np.arctan2(*(0.5 * (lo + hi) - p)[::-1]) + 0.5 * rng.standard_normal()
            seg = rng.uniform(cfg.segment_min_m, cfg.segment_max_m)
            q = p + seg * np.array([np.cos(h), np.sin(h)])
            if free(q) and _segment_clear(p, q, centres, radii):
                chosen, heading = q, h
                break
        if chosen is None:  # no clear segment: accept a short hop inward
            chosen = p + 0.3 * (0.5 * (lo + hi) - p) + 0.01
        total += float(np.linalg.norm(chosen - p))
        pts.append(chosen)
    return np.array(pts)
