"""The runner's odometry front-end: motion inputs -> odometry steps
(:class:`reloc.odometry.OdometryAssembler`) corrected for wheel slip
(:class:`reloc.slip.SlipMonitor`) and a gyro bias (:class:`reloc.gyro.GyroMonitor`) by what the
landmark frames show.

It depends on the measurements and the runner's config alone, never on a back-end or a fix, so
a comparison's passes would all compute the same steps: :class:`SharedSteps` computes them once
for an in-memory stream and hands them to every pass (the demo: ~10 s of each of five passes on
the slip and gyro registrations). The steps are held as arrays, not objects, so that forked
passes share them without copying (an object's reference count written by a child copies its
page). A stream read from disk at every pass (a bag of more than
:data:`fgslam.inputs.STREAM_ABOVE_MESSAGES` messages) keeps a front-end per pass: its steps would
not fit in memory any better than its measurements.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from reloc.gyro import GyroMonitor
from reloc.measurements import CmdVel, GroundTruthPose, ImuSample, WheelOdometry
from reloc.odometry import OdometryAssembler, OdometryStep
from reloc.rows import RowBuffer
from reloc.slip import SlipMonitor

MOTION_INPUTS = (CmdVel, WheelOdometry, ImuSample)
_SCALARS = ("t0", "t1", "v_mps", "yaw_rate_cmd_radps", "extra_forward_var_m2", "extra_yaw_var_rad2")


class FrontEnd:
    """One pass's front-end, computed as the stream goes (see module doc)."""

    def __init__(self, cfg) -> None:
        self.odometry = OdometryAssembler(speed_source=cfg.speed_source, max_gap_s=cfg.max_imu_gap_s,
                                          max_speed_age_s=cfg.max_speed_age_s)
        self.slip = SlipMonitor(cfg.slip)
        self.gyro = GyroMonitor(cfg.gyro)

    def motion(self, i: int, m) -> OdometryStep | None:
        """The corrected step completed by motion input ``m`` (the stream's ``i``-th measurement), or None."""
        step = self.odometry.push(m)
        return None if step is None else self.gyro.correct(self.slip.correct(step))

    def observe(self, kind: str, m) -> None:
        """A landmark frame of ``kind``: both monitors compare it with their reference."""
        self.slip.observe(kind, m)
        self.gyro.observe(kind, m)

    def stats(self) -> dict:
        return {"slip": self.slip.stats(), "gyro": self.gyro.stats()}


def _config_key(cfg) -> tuple:
    """What of a runner config the front-end depends on."""
    return (cfg.speed_source, cfg.max_imu_gap_s, cfg.max_speed_age_s, cfg.slip, cfg.gyro)


class SharedSteps:
    """The front-end of an in-memory stream computed once (see module doc): per measurement
    index, the row of its step (-1: none), and the steps' fields as arrays. :meth:`for_pass`
    gives a pass a front-end that reads them back; a pass on another stream or with another
    front-end config computes its own."""

    def __init__(self, measurements: list, cfg, kind_of: Callable[[object, float], str]) -> None:
        t0 = time.perf_counter()
        self.measurements, self.key = measurements, _config_key(cfg)
        fe = FrontEnd(cfg)
        row = np.full(len(measurements), -1, dtype=np.int64)
        rows = RowBuffer(len(_SCALARS) + 9 + 9 + 3)  # ~0.2 kB a step; as objects ~1 kB
        for i, m in enumerate(measurements):
            if isinstance(m, MOTION_INPUTS):
                step = fe.motion(i, m)
                if step is not None:
                    row[i] = len(rows)
                    rows.append([*(getattr(step, f) for f in _SCALARS), *np.ravel(step.R_ref_base0),
                                 *np.ravel(step.R_ref_base1), *step.gyro_radps])
            elif not isinstance(m, GroundTruthPose):
                fe.observe(kind_of(m, m.t), m)
        a = rows.array()
        for x in (row, a):
            x.setflags(write=False)  # shared by every pass (in one process when they run in turn)
        k = len(_SCALARS)
        self.row = row
        self.scalars = a[:, :k]
        self.R0 = a[:, k:k + 9].reshape(-1, 3, 3)
        self.R1 = a[:, k + 9:k + 18].reshape(-1, 3, 3)
        self.gyro = a[:, k + 18:]
        self.stats = fe.stats()
        self.seconds = time.perf_counter() - t0

    def matches(self, measurements, cfg) -> bool:
        """Whether these are the steps of ``measurements`` (the very list) under ``cfg``."""
        return measurements is self.measurements and _config_key(cfg) == self.key

    def for_pass(self) -> _Replayed:
        return _Replayed(self)


class _Replayed:
    """A pass's front-end reading :class:`SharedSteps` back (the same steps, value for value)."""

    def __init__(self, shared: SharedSteps) -> None:
        self.shared = shared

    def motion(self, i: int, m) -> OdometryStep | None:
        s = self.shared
        k = int(s.row[i])
        if k < 0:
            return None
        t0, t1, v, w, fwd, yaw = s.scalars[k].tolist()
        return OdometryStep(t0, t1, v, w, s.R0[k], s.R1[k], s.gyro[k], fwd, yaw)

    def observe(self, kind: str, m) -> None:
        pass  # the monitors saw every frame when the steps were computed

    def stats(self) -> dict:
        return self.shared.stats
