"""Fast CDR encoding of the simulator's bag messages (the hot loop of a kilometre run).

rosbags builds a message object per message (and per rock detection) and serialises it field by
field; at 120 messages per simulated second plus a Detection3DArray of ~100 rocks at 2 Hz that is
most of a long run's time. The messages the simulator writes have a fixed layout once their frame
ids are fixed, so each type here is one precompiled :class:`struct.Struct` (little-endian CDR,
alignment relative to the payload after the 4-byte encapsulation header, as ROS 2 writes it).
:func:`check_against_rosbags` encodes sample messages both ways and must find them byte-identical;
:func:`sim.bag_writer.write_bag` runs it before it uses these encoders (and falls back to rosbags
otherwise).
"""

from __future__ import annotations

import struct
from functools import lru_cache

import numpy as np

from reloc.measurements import CmdVel, GroundTruthPose, ImuSample, RockObservations, WheelOdometry

CDR_LE_HEADER = b"\x00\x01\x00\x00"


class _Layout:
    """Builds a struct format for a CDR payload: fields appended in order, aligned to their size."""

    def __init__(self, pos: int = 0) -> None:
        self.fmt = ["<"]
        self.pos = pos

    def _align(self, n: int) -> None:
        pad = (-self.pos) % n
        if pad:
            self.fmt.append(f"{pad}x")
            self.pos += pad

    def u32(self, n: int = 1) -> _Layout:
        self._align(4)
        self.fmt.append(f"{n}I")
        self.pos += 4 * n
        return self

    def i32(self) -> _Layout:
        self._align(4)
        self.fmt.append("i")
        self.pos += 4
        return self

    def f64(self, n: int = 1) -> _Layout:
        self._align(8)
        self.fmt.append(f"{n}d")
        self.pos += 8 * n
        return self

    def string(self, s: str) -> _Layout:
        self.u32()
        k = len(s.encode()) + 1
        self.fmt.append(f"{k}s")
        self.pos += k
        return self

    def header(self, frame_id: str) -> _Layout:
        return self.i32().u32().string(frame_id)

    def struct(self) -> struct.Struct:
        return struct.Struct("".join(self.fmt))


def _sb(s: str) -> bytes:
    return s.encode() + b"\0"


class FastEncoder:
    """Encoders of the five measurement types for the frame ids and covariances of a bag
    (the same content as :class:`sim.bag_writer._Encoder` builds)."""

    def __init__(self, frame_base: str, world_frame: str, class_id: str, imu_cov: tuple, wheel_cov: tuple,
                 rock_rotation_var: float) -> None:
        self.base, self.world, self.class_id = frame_base, world_frame, class_id
        self.base_b, self.world_b, self.odom_b, self.class_b = _sb(frame_base), _sb(world_frame), _sb("odom"), _sb(class_id)
        self.imu_ocov, self.imu_gcov, self.imu_acov = (tuple(float(v) for v in c) for c in imu_cov)
        self.wheel_pcov, self.wheel_tcov = (tuple(float(v) for v in c) for c in wheel_cov)
        self.rot_var = float(rock_rotation_var)
        self._twist = _Layout().header(frame_base).f64(6).struct()
        self._imu = _Layout().header(frame_base).f64(4).f64(9).f64(3).f64(9).f64(3).f64(9).struct()
        self._odom = {f: _Layout().header(f).string(frame_base).f64(7).f64(36).f64(6).f64(36).struct()
                      for f in ("odom", world_frame)}

    @staticmethod
    def _stamp(ns: int) -> tuple[int, int]:
        return divmod(ns, 1_000_000_000)

    def cmd_vel(self, m: CmdVel, ns: int) -> bytes:
        s, n = self._stamp(ns)
        return CDR_LE_HEADER + self._twist.pack(s, n, len(self.base_b), self.base_b, m.v_mps, 0.0, 0.0, 0.0, 0.0,
                                                m.yaw_rate_radps)

    def imu(self, m: ImuSample, ns: int) -> bytes:
        s, n = self._stamp(ns)
        return CDR_LE_HEADER + self._imu.pack(s, n, len(self.base_b), self.base_b, *m.quat_xyzw.tolist(), *self.imu_ocov,
                                              *m.gyro_radps.tolist(), *self.imu_gcov, *m.accel_mps2.tolist(), *self.imu_acov)

    def wheel(self, m: WheelOdometry, ns: int) -> bytes:
        s, n = self._stamp(ns)
        return CDR_LE_HEADER + self._odom["odom"].pack(
            s, n, len(self.odom_b), self.odom_b, len(self.base_b), self.base_b, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            *self.wheel_pcov, m.v_mps, 0.0, 0.0, 0.0, 0.0, m.yaw_rate_radps, *self.wheel_tcov)

    def ground_truth(self, m: GroundTruthPose, ns: int) -> bytes:
        s, n = self._stamp(ns)
        return CDR_LE_HEADER + self._odom[self.world].pack(
            s, n, len(self.world_b), self.world_b, len(self.base_b), self.base_b, *m.position_m.tolist(),
            *m.quat_xyzw.tolist(), *([0.0] * 36), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, *([0.0] * 36))

    def rocks(self, m: RockObservations, ns: int) -> bytes:
        s, n = self._stamp(ns)
        N = len(m)
        head = (s, n, len(self.base_b), self.base_b, N)
        if N == 0:
            return CDR_LE_HEADER + _rocks_struct(self.base, self.class_id, 0).pack(*head)
        cov6 = np.zeros((N, 6, 6))
        cov6[:, :3, :3] = m.cov_base_m2
        cov6[:, 3, 3] = cov6[:, 4, 4] = cov6[:, 5, 5] = self.rot_var
        xyz = m.xyz_base_m.tolist()
        size = m.size_m.tolist()
        score = m.score.tolist()
        cov = cov6.reshape(N, 36).tolist()
        lb, lc = len(self.base_b), len(self.class_b)
        vals = list(head)
        for i in range(N):
            x, y, z = xyz[i]
            d = size[i]
            vals += (s, n, lb, self.base_b, 1, lc, self.class_b, score[i], x, y, z, 0.0, 0.0, 0.0, 1.0)
            vals += cov[i]
            vals += (x, y, z, 0.0, 0.0, 0.0, 1.0, d, d, d, 1, b"\0")
        return CDR_LE_HEADER + _rocks_struct(self.base, self.class_id, N).pack(*vals)


@lru_cache(maxsize=512)
def _rocks_struct(frame_base: str, class_id: str, n: int) -> struct.Struct:
    lay = _Layout().header(frame_base).u32()
    for _ in range(n):
        lay.header(frame_base).u32().string(class_id).f64().f64(7).f64(36).f64(7).f64(3).string("")
    return lay.struct()


def check_against_rosbags(fast: FastEncoder, slow, samples: list) -> bool:
    """True when ``fast`` and rosbags' serialisation of the message objects ``slow``'s builders make
    (:class:`sim.bag_writer._Encoder`, a kind's codec) agree byte for byte on every (measurement,
    ns, fast method name, builder, msgtype) of ``samples``."""
    for m, ns, name, build, msgtype in samples:
        a = getattr(fast, name)(m, ns)
        b = bytes(slow.ts.serialize_cdr(build(m, ns), msgtype))
        if a != b:
            return False
    return True
