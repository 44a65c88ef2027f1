"""Trajectories in the TUM text format: one pose a line, ``t x y z qx qy qz qw``.

``t`` in seconds, position in metres, the quaternion (Hamilton, x y z w) is the rotation of
base_link in world, so a line is ``T_world_base`` at ``t``. evo and most SLAM tools read this
format; lines starting with ``#`` are comments.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fgslam.errors import InputFileError
from reloc.backend import Trajectory

log = logging.getLogger(__name__)

_QUAT_NORM_TOL = 1e-3
_BLOCK = 65536  # poses checked and converted at once


def write_tum(path: str | Path, t: np.ndarray, T_world_base: np.ndarray) -> None:
    """Write poses ``T_world_base`` (K, 4, 4) at times ``t`` (K,) seconds as a TUM file.

    Raises ValueError on mismatched shapes, non-finite values or non-rotation matrices.
    """
    path = Path(path)
    t = np.asarray(t, dtype=float).reshape(-1)
    T = np.asarray(T_world_base, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] != t.shape[0]:
        raise ValueError(
            f"write_tum: need t (K,) and T_world_base (K, 4, 4), got shapes {t.shape} and {T.shape}"
        )
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(T))):
        raise ValueError("write_tum: t or T_world_base contains NaN or inf")
    R = T[:, :3, :3]
    # block by block: a 24-hour truth is 2.6 M poses, and (K, 3, 3) temporaries at once (the check's
    # product, difference and absolute value, the rotations' copy) were ~0.6 GB at the end of a 10 km run
    quat_xyzw = np.zeros((len(T), 4))
    for k in range(0, len(T), _BLOCK):
        Rk = R[k:k + _BLOCK]
        if np.max(np.abs(Rk @ np.swapaxes(Rk, 1, 2) - np.eye(3))) > 1e-6:
            raise ValueError("write_tum: T_world_base[:, :3, :3] is not a rotation matrix")
        quat_xyzw[k:k + _BLOCK] = Rotation.from_matrix(Rk).as_quat()
    # A fixed sign (w >= 0) keeps files diff-able; q and -q are the same rotation.
    quat_xyzw = np.where(quat_xyzw[:, 3:4] < 0.0, -quat_xyzw, quat_xyzw)
    rows = np.column_stack([t, T[:, :3, 3], quat_xyzw])
    try:
        with path.open("w", encoding="utf-8") as f:
            f.write("# timestamp tx ty tz qx qy qz qw\n")
            for row in rows:
                f.write(" ".join(repr(float(v)) for v in row) + "\n")
    except OSError as exc:
        raise InputFileError(f"cannot write trajectory {path}: {exc.strerror or exc}") from exc


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file into a :class:`Trajectory` (``t`` (K,) s, ``T_world_base`` (K, 4, 4)).

    Malformed lines (wrong field count, non-numbers, NaN, non-unit quaternion) raise
    :class:`InputFileError` naming the file and the line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputFileError(f"cannot read trajectory {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise InputFileError(f"trajectory {path} is not UTF-8 text: {exc}") from exc
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise InputFileError(
                f"trajectory {path}: line {lineno}: {len(fields)} field(s), expected 8 "
                "(t x y z qx qy qz qw)"
            )
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise InputFileError(
                f"trajectory {path}: line {lineno}: non-numeric field in {line!r}"
            ) from None
        if not np.all(np.isfinite(values)):
            raise InputFileError(f"trajectory {path}: line {lineno}: NaN or inf in {line!r}")
        norm = float(np.linalg.norm(values[4:]))
        if abs(norm - 1.0) > _QUAT_NORM_TOL:
            raise InputFileError(
                f"trajectory {path}: line {lineno}: quaternion norm {norm:.6f} is not 1"
            )
        rows.append(values)
    if not rows:
        raise InputFileError(f"trajectory {path}: no poses")
    arr = np.asarray(rows, dtype=float)
    T = np.tile(np.eye(4), (len(arr), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(arr[:, 4:8]).as_matrix()  # normalises the quaternions
    T[:, :3, 3] = arr[:, 1:4]
    log.debug("read %d poses from %s", len(arr), path)
    return Trajectory(t=arr[:, 0].copy(), T_world_base=T)
