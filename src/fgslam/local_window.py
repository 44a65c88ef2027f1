"""The relocalizer's local map: a bounded window of the recent path.

A back-end bounds its own map (the EKF marginalises what it has left behind, the fixed-lag
smoother freezes and finally drops what left its window), but where rocks are sparse the map of
the last few metres holds too few catalogued rocks to match, and matches get more frequent as the
map grows. So the relocalizer keeps, beside the back-end's current map, the landmarks the
back-end has dropped, as long as they were last seen within ``path_m`` metres of estimated path,
at most ``max_kept`` of them: a map that grows with the path up to a bound and never forever.

Dropped landmarks keep the estimate they had when last seen; when the back-end's frame moves
(a fix corrects it), the landmarks still in both its previous and its current map give the planar
rigid motion between the two, which is applied to the dropped ones, so the window stays in one
frame with the back-end's map.
"""

from __future__ import annotations

import numpy as np

from reloc.backend import LandmarkMap


def rigid_2d(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation (2, 2) and translation (2,) with ``dst ~ R @ src + t`` for (K, 2)
    point pairs; the identity for no pair, a translation for one."""
    if len(src) == 0:
        return np.eye(2), np.zeros(2)
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    if len(src) == 1:
        return np.eye(2), cd - cs
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


class LocalMapWindow:
    """The back-end's map of one kind plus the landmarks it dropped within the last ``path_m``
    metres of estimated path (at most ``max_kept``); see the module doc."""

    def __init__(self, path_m: float, max_kept: int) -> None:
        self.path_m = float(path_m)
        self.max_kept = int(max_kept)
        self.path_done_m = 0.0
        self._last_xy: np.ndarray | None = None
        self._prev: dict[int, np.ndarray] = {}  # id -> planar position in the previous snapshot
        self._kept: dict[int, tuple] = {}  # dropped id -> (xyz, cov, size, n_obs, path at last sight, catalog row)
        self._last: LandmarkMap | None = None  # the previous snapshot
        self.n_kept_max = 0

    def __len__(self) -> int:
        return len(self._kept)

    def update(self, lmap: LandmarkMap, xy_rover: np.ndarray) -> LandmarkMap:
        """Take the snapshot ``lmap`` made with the rover at ``xy_rover`` (2,); returns it with the
        kept dropped landmarks appended (their ids are the back-end's)."""
        xy_rover = np.asarray(xy_rover, float)[:2]
        if self._last_xy is not None:
            self.path_done_m += float(np.hypot(*(xy_rover - self._last_xy)))
        self._last_xy = xy_rover
        ids = lmap.ids.astype(int)
        now = {int(i): lmap.xyz_world_m[r, :2] for r, i in enumerate(ids)}
        common = [i for i in now if i in self._prev]
        gone = [i for i in self._prev if i not in now]
        if self._kept and common:
            R, t = rigid_2d(np.array([self._prev[i] for i in common]), np.array([now[i] for i in common]))
            if not (np.allclose(R, np.eye(2)) and np.allclose(t, 0.0)):
                for i, (xyz, cov, size, n_obs, seen, row) in self._kept.items():
                    xyz = xyz.copy()
                    xyz[:2] = R @ xyz[:2] + t
                    cov = cov.copy()
                    cov[:2, :2] = R @ cov[:2, :2] @ R.T
                    self._kept[i] = (xyz, cov, size, n_obs, seen, row)
        if gone:
            last = self._last
            rows = {int(i): r for r, i in enumerate(last.ids)}
            for i in gone:
                r = rows.get(i)
                if r is not None:
                    self._kept[i] = (last.xyz_world_m[r].copy(), last.cov_world_m2[r].copy(), float(last.size_m[r]),
                                     int(last.n_obs[r]), self.path_done_m, int(last.anchored_rows[r]))
        for i in [i for i in self._kept if i in now]:  # back in the back-end's map
            del self._kept[i]
        old = [i for i, rec in self._kept.items() if self.path_done_m - rec[4] > self.path_m]
        for i in old:
            del self._kept[i]
        while len(self._kept) > self.max_kept:  # oldest first (insertion order)
            del self._kept[next(iter(self._kept))]
        self.n_kept_max = max(self.n_kept_max, len(self._kept))
        self._prev, self._last = now, lmap
        if not self._kept:
            return lmap
        recs = list(self._kept.items())
        return LandmarkMap(
            ids=np.concatenate([ids, np.array([i for i, _ in recs], dtype=int)]),
            xyz_world_m=np.vstack([lmap.xyz_world_m.reshape(-1, 3), np.array([r[0] for _, r in recs])]),
            cov_world_m2=np.concatenate([lmap.cov_world_m2.reshape(-1, 3, 3), np.array([r[1] for _, r in recs])]),
            size_m=np.concatenate([lmap.size_m, np.array([r[2] for _, r in recs])]),
            n_obs=np.concatenate([lmap.n_obs, np.array([r[3] for _, r in recs], dtype=int)]),
            kind=lmap.kind,
            catalog_row=np.concatenate([lmap.anchored_rows, np.array([r[5] for _, r in recs], dtype=int)]),
        )
