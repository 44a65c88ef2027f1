"""The filter state: pose, landmarks, joint covariance, landmark book and schedule clocks.

Layout of the error state (and of ``P``): ``[dp_world (3), dtheta_world (3), (de (3), ds (1)),
(db (1)), (dg (1), (dk (1)), (do (1))), (df_src (3) per fix source), dl_0 (3), dl_1 (3), ...]`` with ``R_true = Exp(dtheta) R``: the convention of
:mod:`reloc.backend`, so the pose block of ``P`` is directly the pose covariance of
:class:`reloc.backend.PoseEstimate`. The optional calibration block (``head`` 10 instead of 6)
holds the stereo measurements' rotation error ``E_true = Exp(de) E`` and scale ``s_true = s + ds``
(see :class:`reloc.calibration.CalibrationConfig`). The optional yaw-rate bias ``b`` (rad/s) is the
rate at which the IMU's reported heading drifts about world z (its gyro bias, once the IMU's own
gravity reference has taken out roll and pitch). The optional slip ``g`` is the share of the
commanded distance the wheels lose to the soil (``v_true = (1 - g - k theta - o) v``), a bias that a white model
of slip cannot represent; the optional ``k`` is its growth per rad of uphill pitch ``theta`` and
the optional ``o`` its first-order Gauss-Markov wander with the soil. The optional ``f_src`` is the
(x, y, yaw) error that one catalog's fixes share (``FixGateConfig.correlation_model`` "bias"). The landmarks ``dl_i`` are 3D points of every
landmark kind in one block; ``book.kind`` tags each with its kind (:mod:`ekf.kinds`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from reloc.geometry import exp_so3, project_so3
from reloc.landmark_book import LandmarkBook
from reloc.persistence import PendingDetections, RecentDetections, RecentFrames

POSE_DIM = 6
CALIB_DIM = 4  # rotation error (3) and range scale (1) of the stereo measurements


def take_symmetric(P: np.ndarray, cols: np.ndarray, max_runs: int = 12) -> np.ndarray:
    """``P[np.ix_(cols, cols)]`` for sorted ``cols``, copied as contiguous blocks when ``cols`` is a
    few runs of consecutive indices (dropping a few landmarks): several times faster than fancy
    indexing for a large ``P``."""
    breaks = np.flatnonzero(np.diff(cols) != 1) + 1
    if len(breaks) + 1 > max_runs:
        return P[np.ix_(cols, cols)]
    starts = np.concatenate([[0], breaks])
    stops = np.concatenate([breaks, [len(cols)]])
    out = np.empty((len(cols), len(cols)), dtype=P.dtype)
    for a0, a1 in zip(starts, stops):
        ra = slice(cols[a0], cols[a1 - 1] + 1)
        for b0, b1 in zip(starts, stops):
            out[a0:a1, b0:b1] = P[ra, cols[b0]:cols[b1 - 1] + 1]
    return out


@dataclass
class FilterState:
    """Mutable filter state; :meth:`copy` gives an independent snapshot (checkpoints)."""

    t: float  # time of the pose (end of the last step)
    t_input: float  # newest input time processed (step end or landmark frame)
    p_world: np.ndarray  # (3,)
    R_world_base: np.ndarray  # (3, 3)
    l_world: np.ndarray  # (n, 3)
    P: np.ndarray  # (6 + 3n, 6 + 3n)
    book: LandmarkBook
    t_last_attitude: float
    t_last_checkpoint: float
    n_steps_since_orthonormalise: int = 0
    fix_times: tuple = ()  # t_meas of the fixes applied to this state, oldest first
    fix_last_xy: dict = field(default_factory=dict)  # source -> the estimate's (x, y) at the last fix applied from it
    fix_last_rows: dict = field(default_factory=dict)  # source -> the catalog entries of its last fix applied
    fix_bias_cols: dict = field(default_factory=dict)  # source -> first column of its (x, y, yaw) fix offset
    fix_bias: dict = field(default_factory=dict)  # source -> (3,) its fixes' (x, y, yaw) offset
    head: int = POSE_DIM  # states before the landmarks: the pose, then the calibration, yaw-rate bias and slip when on
    n_calib: int = 0  # CALIB_DIM when the calibration is estimated, else 0
    bias_col: int = -1  # column of the yaw-rate bias in P, -1 when not estimated
    yaw_bias: float = 0.0  # rad/s: IMU heading drift about world z, R_imu ~ Exp(b t e_z) R_true
    slip_col: int = -1  # column of the wheel slip in P, -1 when not estimated
    slip: float = 0.0  # the share of the commanded distance not driven: v_true = (1 - slip) v
    slope_col: int = -1  # column of the slip's gain per rad of uphill pitch, -1 when not estimated
    slope_gain: float = 0.0  # slip = slip + slope_gain * uphill pitch (rad)
    gm_col: int = -1  # column of the slip's Gauss-Markov term, -1 when not estimated
    slip_gm: float = 0.0  # slip = slip + slope_gain * uphill + slip_gm
    calib_R: np.ndarray = field(default_factory=lambda: np.eye(3))  # E: true base point -> measured
    calib_s: float = 1.0  # measured / true range
    t_last_frame: dict = field(default_factory=dict)  # kind name -> time of its last frame used
    reserved: dict = field(default_factory=dict)  # kind code -> landmark slots it holds (from its first frame)
    # First-estimate Jacobians (EkfConfig.first_estimate_jacobians): the position the pose was
    # propagated to (its prior at the next update) and each landmark's position as initialised
    # from that prior. The Jacobians that couple rotation to position are evaluated there, so
    # the linearised filter keeps SLAM's unobservable directions (a common translation, a yaw
    # about world z) and gains no yaw information from landmarks alone. None: off.
    p_lin: np.ndarray | None = None  # (3,)
    l_lin: np.ndarray | None = None  # (n, 3)
    recent: RecentDetections = field(default_factory=RecentDetections)  # landmarks' recent detections (persistence)
    pending: dict = field(default_factory=dict)  # kind code -> PendingDetections: first sightings (persistence)
    frames: dict = field(default_factory=dict)  # kind code -> RecentFrames: every recent detection (place rule)

    @property
    def calibrated(self) -> bool:
        return self.n_calib > 0

    @property
    def has_yaw_bias(self) -> bool:
        return self.bias_col >= 0

    @property
    def has_slip(self) -> bool:
        return self.slip_col >= 0

    @property
    def has_slope_slip(self) -> bool:
        return self.slope_col >= 0

    @property
    def has_slip_gm(self) -> bool:
        return self.gm_col >= 0

    def slip_at(self, uphill_rad: float) -> float:
        """The share of the commanded distance lost on a slope of ``uphill_rad`` (nose up positive)."""
        return self.slip + self.slope_gain * uphill_rad + self.slip_gm  # both 0 unless states

    @property
    def n_landmarks(self) -> int:
        return int(self.l_world.shape[0])

    def copy(self) -> FilterState:
        """Deep copy of every array and the landmark book."""
        return FilterState(
            t=self.t,
            t_input=self.t_input,
            p_world=self.p_world.copy(),
            R_world_base=self.R_world_base.copy(),
            l_world=self.l_world.copy(),
            P=self.P.copy(),
            book=self.book.copy(),
            t_last_attitude=self.t_last_attitude,
            t_last_frame=dict(self.t_last_frame),
            reserved=dict(self.reserved),
            t_last_checkpoint=self.t_last_checkpoint,
            n_steps_since_orthonormalise=self.n_steps_since_orthonormalise,
            fix_times=self.fix_times,
            fix_last_xy=dict(self.fix_last_xy),
            fix_last_rows=dict(self.fix_last_rows),
            fix_bias_cols=self.fix_bias_cols,  # fixed at construction
            fix_bias={k: v.copy() for k, v in self.fix_bias.items()},
            head=self.head,
            n_calib=self.n_calib,
            bias_col=self.bias_col,
            yaw_bias=self.yaw_bias,
            slip_col=self.slip_col,
            slip=self.slip,
            slope_col=self.slope_col,
            slope_gain=self.slope_gain,
            gm_col=self.gm_col,
            slip_gm=self.slip_gm,
            calib_R=self.calib_R.copy(),
            calib_s=self.calib_s,
            p_lin=None if self.p_lin is None else self.p_lin.copy(),
            l_lin=None if self.l_lin is None else self.l_lin.copy(),
            recent=self.recent.copy(),
            pending={code: p.copy() for code, p in self.pending.items()},
            frames={code: f.copy() for code, f in self.frames.items()},
        )

    def inject(self, dx: np.ndarray) -> None:
        """Apply an error-state correction ``dx`` (head + 3n,) to the nominal state."""
        self.p_world = self.p_world + dx[:3]
        self.R_world_base = exp_so3(dx[3:6]) @ self.R_world_base
        if self.calibrated:
            self.calib_R = exp_so3(dx[6:9]) @ self.calib_R
            self.calib_s = self.calib_s + float(dx[9])
        if self.bias_col >= 0:
            self.yaw_bias = self.yaw_bias + float(dx[self.bias_col])
        if self.slip_col >= 0:
            self.slip = self.slip + float(dx[self.slip_col])
        if self.slope_col >= 0:
            self.slope_gain = self.slope_gain + float(dx[self.slope_col])
        if self.gm_col >= 0:
            self.slip_gm = self.slip_gm + float(dx[self.gm_col])
        for src, c in self.fix_bias_cols.items():
            self.fix_bias[src] = self.fix_bias[src] + dx[c:c + 3]
        if self.n_landmarks:
            self.l_world = self.l_world + dx[self.head:].reshape(-1, 3)

    @property
    def first_estimates(self) -> bool:
        return self.p_lin is not None

    def jacobian_points(self, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The pose position (3,) and landmark positions (k, 3) (``rows``, all when None) that the
        rotation-to-position Jacobians are evaluated at: the first estimates when kept, else the
        current estimate."""
        if self.p_lin is None:
            l = self.l_world
            return self.p_world, l if rows is None else l[rows]
        return self.p_lin, self.l_lin if rows is None else self.l_lin[rows]

    def reset_first_estimates(self) -> None:
        """Linearise at the current estimate from now on (after a global fix, which observes
        what SLAM alone cannot, the old first estimates would only be a worse linearisation)."""
        if self.p_lin is not None:
            self.p_lin = self.p_world.copy()
            self.l_lin = self.l_world.copy()

    def refresh_first_estimates(self, tol_m: float) -> bool:
        """Re-linearise everything at the current estimate when a correction has moved the pose
        more than ``tol_m`` (m) from its first estimate (a re-anchoring on a map the filter had
        wrong, where the first estimate is no longer a linearisation point). Landmarks keep
        theirs whatever their corrections: re-linearising a landmark gives the filter yaw
        information it does not have. True when it re-linearised."""
        if self.p_lin is None or float(np.sum((self.p_world - self.p_lin) ** 2)) <= tol_m * tol_m:
            return False
        self.reset_first_estimates()
        return True

    def orthonormalise(self) -> None:
        """Remove the round-off drift of the rotation matrices."""
        self.R_world_base = project_so3(self.R_world_base)
        if self.calibrated:
            self.calib_R = project_so3(self.calib_R)
        self.n_steps_since_orthonormalise = 0

    def pad_head(self, J: np.ndarray) -> np.ndarray:
        """Jacobians (..., w) over the first ``w`` head states, zero-padded to (..., head): the
        states that do not enter a measurement (the yaw-rate bias, the slip) get zero columns."""
        if J.shape[-1] == self.head:
            return J
        out = np.zeros(J.shape[:-1] + (self.head,))
        out[..., : J.shape[-1]] = J
        return out

    def yaw_bias_step(self, dt: float, walk_var: float) -> None:
        """The bias's share of a prediction over ``dt``: ``dtheta -= e_z dt db`` on the rows and
        columns of P (O(n)), then the bias random walk ``walk_var`` (rad^2/s^2)."""
        b, th = self.bias_col, 5  # world z of dtheta_world
        P = self.P
        P[th, :] -= dt * P[b, :]
        P[:, th] -= dt * P[:, b]
        P[:, th] = P[th, :]  # exactly symmetric (the two passes round differently)
        P[b, b] += walk_var

    def slip_step(self, d_world: np.ndarray, walk_var: float, uphill_rad: float = 0.0,
                  slope_walk_var: float = 0.0, gm_decay: float = 1.0, gm_var: float = 0.0) -> None:
        """The slip's share of a prediction that drove ``d_world`` (3,) (the commanded motion
        times ``1 - slip_at(uphill_rad)``): ``dp -= u (dslip + uphill_rad dgain + dgm)`` with
        ``u = d_world / (1 - slip_at(uphill_rad))``, on the rows and columns of P (O(n)); then
        the random walks ``walk_var`` (slip) and ``slope_walk_var`` (its slope gain), and the
        Gauss-Markov term's decay ``gm_decay`` (exp(-dt / tau)) and its noise ``gm_var``."""
        u = d_world / (1.0 - self.slip_at(uphill_rad))
        cols, U = [self.slip_col], [u]
        if self.has_slope_slip:
            cols.append(self.slope_col)
            U.append(uphill_rad * u)
        if self.has_slip_gm:
            cols.append(self.gm_col)
            U.append(u)
        U = np.column_stack(U)
        P = self.P
        P[:3, :] -= U @ P[cols, :]
        P[:, :3] -= P[:, cols] @ U.T  # with the rows just updated: + U P_cc U^T
        P[:3, :3] = 0.5 * (P[:3, :3] + P[:3, :3].T)  # exactly symmetric (the two passes round differently)
        P[3:, :3] = P[:3, 3:].T
        P[self.slip_col, self.slip_col] += walk_var
        if self.has_slope_slip:
            P[self.slope_col, self.slope_col] += slope_walk_var
        if self.has_slip_gm:
            k = self.gm_col
            self.slip_gm *= gm_decay
            P[k, :] *= gm_decay
            P[:, k] *= gm_decay
            P[k, k] += gm_var

    def landmark_cols(self, rows: np.ndarray) -> np.ndarray:
        """State columns (3k,) of the landmarks at ``rows`` (k,)."""
        rows = np.asarray(rows, dtype=int)
        return (self.head + 3 * rows[:, None] + np.arange(3)[None, :]).reshape(-1)

    def landmark_cov_blocks(self, rows: np.ndarray) -> np.ndarray:
        """Marginal covariances (k, 3, 3) of the landmarks at ``rows``."""
        cols = self.landmark_cols(rows).reshape(-1, 3)
        return self.P[cols[:, :, None], cols[:, None, :]]

    def head_landmark_cov(self, rows: np.ndarray) -> np.ndarray:
        """Cross covariances (k, head, 3) of the pose (and calibration) with the landmarks at ``rows``."""
        cols = self.landmark_cols(rows).reshape(-1, 3)
        return np.transpose(self.P[: self.head][:, cols], (1, 0, 2))

    def append_landmarks(self, l_new: np.ndarray, G_head: np.ndarray, cov_meas_world: np.ndarray) -> None:
        """Initialise k landmarks ``l_new`` (k, 3) from ``l = f(pose, calibration, z)`` with
        Jacobian ``G_head`` (k, 3, head) w.r.t. the head states and measurement covariance in world
        ``cov_meas_world`` (k, 3, 3); their cross covariances with the whole state are ``G P[head, :]``."""
        k = l_new.shape[0]
        if k == 0:
            return
        n_old = self.P.shape[0]
        G = G_head.reshape(3 * k, self.head)
        cross = G @ self.P[: self.head]  # (3k, N)
        P_new = np.empty((n_old + 3 * k, n_old + 3 * k))
        P_new[:n_old, :n_old] = self.P
        P_new[n_old:, :n_old] = cross
        P_new[:n_old, n_old:] = cross.T
        block = cross[:, : self.head] @ G.T
        for i in range(k):
            block[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += cov_meas_world[i]
        P_new[n_old:, n_old:] = 0.5 * (block + block.T)
        self.P = P_new
        if self.l_lin is not None:  # initialised from the pose's first estimate (same measurement)
            self.l_lin = np.vstack([self.l_lin, l_new - (self.p_world - self.p_lin)])
        self.l_world = np.vstack([self.l_world, l_new])

    def pending_for(self, code: int) -> PendingDetections:
        """The first sightings of kind ``code`` (created on first use)."""
        return self.pending.setdefault(code, PendingDetections())

    def frames_for(self, code: int) -> RecentFrames:
        """Every recent detection of kind ``code`` by place (created on first use)."""
        return self.frames.setdefault(code, RecentFrames())

    def keep_landmarks(self, keep: np.ndarray) -> None:
        """Marginalise out the landmarks where ``keep`` (n,) is False (drop their rows/columns)."""
        keep = np.asarray(keep, dtype=bool)
        if keep.all():
            return
        cols = np.concatenate([np.arange(self.head), self.landmark_cols(np.flatnonzero(keep))])
        self.P = take_symmetric(self.P, cols)
        self.l_world = self.l_world[keep]
        if self.l_lin is not None:
            self.l_lin = self.l_lin[keep]
        self.book.keep(keep)
