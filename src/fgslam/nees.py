"""Two-sided consistency tests on NEES (normalized estimation error squared), pure numpy/scipy.

A consistent estimator's NEES ``e^T P^-1 e`` of an ``n``-dimensional error is chi-square with ``n``
degrees of freedom, so its mean is ``n``. The test is two-sided (Bar-Shalom, Li and Kirubarajan,
*Estimation with Applications to Tracking and Navigation*, 5.4): a mean far *below* ``n`` says the
covariance is too large (pessimistic), far above says it is too small (optimistic); both are
failures. For ``N`` independent NEES samples, ``N * mean ~ chi2(N n)``, which gives the 95 %
interval of the mean: ``[chi2.ppf(0.025, N n) / N, chi2.ppf(0.975, N n) / N]``.

Across Monte Carlo runs (seeds), the samples are independent and this is Bar-Shalom's ANEES test.
Along one run they are not: a SLAM error drifts slowly, so consecutive NEES values are strongly
correlated and the interval for ``N`` raw samples would be far too narrow. A single run's mean is
therefore tested with its *effective* sample size ``N_eff = N / tau``, ``tau`` the integrated
autocorrelation time of the NEES series (Sokal's automatic window, ``M >= 5 tau(M)``).

``tau`` is estimated under the hypothesis being tested: from the *whitened errors*
``w = L^-1 e`` (``P = L L^T``), whose mean under it is zero, not from the NEES's fluctuations about
its own sample mean. For Gaussian errors the NEES ``|w|^2`` has the autocorrelation
``rho(k) = sum_cd r_cd(k)^2 / sum_cd r_cd(0)^2`` (Isserlis), ``r_cd`` the cross-correlations of the
whitened components about zero: an AR(1) error gets the textbook ``(1 + a^2) / (1 - a^2)``, and a
persistent offset, which looks like independent samples to an estimate about the sample mean,
counts as the single draw it is (``N_eff`` about 1). :func:`whitened_test` is that test;
:func:`nees_test` takes a bare NEES series (independent samples, or the series' own
autocorrelation when only the NEES is known). Runs are combined (ANEES across seeds) by pooling:
the mean of all samples, tested with the sum of the runs' effective sizes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from enum import Enum

import numpy as np

from fgslam.errors import FgslamError

PROBABILITY = 0.95  # two-sided acceptance probability of the interval
SOKAL_WINDOW_C = 5.0  # Sokal's window constant for the integrated autocorrelation time


class NeesError(FgslamError):
    """A NEES test asked for something it cannot do (dof < 1, no samples to pool of one dimension)."""


class Verdict(str, Enum):
    """Outcome of a two-sided NEES test."""

    CONSISTENT = "consistent"
    OPTIMISTIC = "optimistic"  # NEES above the interval: covariance too small
    PESSIMISTIC = "pessimistic"  # NEES below the interval: covariance too large
    UNTESTED = "untested"  # no finite sample


def nees_interval(dof: int, n: float, probability: float = PROBABILITY) -> tuple[float, float]:
    """Two-sided ``probability`` interval of the mean of ``n`` independent chi2(``dof``) samples.

    ``n`` may be fractional (an effective sample size); returns (lo, hi), bounds on the mean NEES.
    """
    from scipy.stats import chi2

    if dof < 1 or not n > 0 or not 0.0 < probability < 1.0:
        raise NeesError(f"nees_interval needs dof >= 1, n > 0, 0 < probability < 1; got {dof}, {n}, {probability}")
    a = 0.5 * (1.0 - probability)
    k = dof * float(n)
    return float(chi2.ppf(a, k) / n), float(chi2.ppf(1.0 - a, k) / n)


def _sokal_tau(acf: np.ndarray) -> float:
    """``tau = 1 + 2 sum_k rho_k`` of a normalized autocorrelation ``acf`` (acf[0] = 1), with
    Sokal's automatic window; clipped to [1, len(acf)]."""
    n = acf.size
    taus = 2.0 * np.cumsum(acf) - 1.0  # tau(M) = 1 + 2 sum_{k=1..M} rho_k
    window = np.flatnonzero(np.arange(n) >= SOKAL_WINDOW_C * taus)
    tau = taus[window[0]] if window.size else taus[-1]
    return float(min(max(tau, 1.0), n))


def _cross_correlations(x: np.ndarray) -> np.ndarray:
    """Raw lagged products ``sum_t x_tc x_(t+k)d`` of a (n, d) series about zero: (d, d, n)."""
    n = x.shape[0]
    m = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, m, axis=0)  # (m/2+1, d)
    return np.fft.irfft(np.conj(f)[:, :, None] * f[:, None, :], m, axis=0)[:n].transpose(1, 2, 0)


def integrated_autocorrelation_time(x: np.ndarray) -> float:
    """Integrated autocorrelation time ``tau = 1 + 2 sum_k rho_k`` of a 1D series (>= 1), about its
    sample mean, with Sokal's automatic window (the smallest ``M`` with ``M >= 5 tau(M)``); 1 for
    fewer than 4 samples or a constant series."""
    x = np.asarray(x, dtype=float)
    if x.size < 4:
        return 1.0
    d = x - x.mean()
    var = float(d @ d)
    if var <= 0.0:
        return 1.0
    return _sokal_tau(_cross_correlations(d[:, None])[0, 0] / var)


def nees_autocorrelation_time(w: np.ndarray) -> float:
    """Integrated autocorrelation time of the NEES ``|w_t|^2`` of whitened errors ``w`` (n, dof),
    estimated about zero (see the module doc): ``rho(k) = sum_cd r_cd(k)^2 / sum_cd r_cd(0)^2``,
    Sokal's window; 1 for fewer than 4 samples or all-zero errors."""
    w = np.asarray(w, dtype=float)
    if w.ndim == 1:
        w = w[:, None]
    if w.shape[0] < 4:
        return 1.0
    power = np.einsum("tc,tc->c", w, w)
    if not np.all(power > 0.0):
        return 1.0
    r = _cross_correlations(w) / np.sqrt(np.outer(power, power))[:, :, None]
    rho = np.einsum("cdk,cdk->k", r, r)
    return _sokal_tau(rho / rho[0])


def whiten(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Whitened errors ``L^-1 e`` (K, d) of errors ``e`` (K, d) with covariances ``P`` (K, d, d),
    ``L`` the lower Cholesky factor (continuous in ``P``, so consecutive stamps' components stay
    comparable); ``|L^-1 e|^2`` is the NEES. Rows whose ``P`` is not positive definite are NaN."""
    e = np.asarray(e, dtype=float)
    P = np.asarray(P, dtype=float)
    if e.ndim == 1:
        e, P = e[:, None], P.reshape(-1, 1, 1)
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    w = np.full(e.shape, np.nan)
    finite = np.all(np.isfinite(P), axis=(1, 2)) & np.all(np.isfinite(e), axis=1)
    ok = np.zeros(len(e), dtype=bool)
    if finite.any():
        ok[finite] = np.linalg.eigvalsh(P[finite])[:, 0] > 0.0
    if ok.any():
        L = np.linalg.cholesky(P[ok])
        w[ok] = np.linalg.solve(L, e[ok][:, :, None])[:, :, 0]
    return w


@dataclass(frozen=True)
class NeesTest:
    """A two-sided test of the mean NEES of ``dof``-dimensional errors.

    ``n`` samples, ``n_eff`` the effective number of independent ones, ``interval`` the
    :data:`PROBABILITY` bounds on the mean for ``n_eff`` samples, ``verdict`` where ``mean`` falls.
    """

    dof: int
    mean: float
    n: int
    n_eff: float
    interval: tuple[float, float]
    verdict: Verdict

    def to_dict(self) -> dict:
        d = asdict(self)
        d["interval"] = list(self.interval)
        d["verdict"] = self.verdict.value
        return d

    @staticmethod
    def from_dict(d: dict) -> NeesTest:
        """Back from :meth:`to_dict` (results files, campaign records)."""
        return NeesTest(int(d["dof"]), float(d["mean"]), int(d["n"]), float(d["n_eff"]),
                        (float(d["interval"][0]), float(d["interval"][1])), Verdict(d["verdict"]))

    @property
    def consistent(self) -> bool:
        return self.verdict is Verdict.CONSISTENT


def _verdict(mean: float, interval: tuple[float, float]) -> Verdict:
    if not np.isfinite(mean):
        return Verdict.UNTESTED
    if mean > interval[1]:
        return Verdict.OPTIMISTIC
    if mean < interval[0]:
        return Verdict.PESSIMISTIC
    return Verdict.CONSISTENT


def _test(dof: int, mean: float, n: int, n_eff: float, probability: float) -> NeesTest:
    if n == 0 or not n_eff > 0:
        nan = float("nan")
        return NeesTest(dof, nan, n, 0.0, (nan, nan), Verdict.UNTESTED)
    interval = nees_interval(dof, n_eff, probability)
    return NeesTest(dof, float(mean), int(n), float(n_eff), interval, _verdict(mean, interval))


def nees_test(nees: np.ndarray, dof: int, correlated: bool = True, probability: float = PROBABILITY) -> NeesTest:
    """Test one run's NEES series (K,) of ``dof``-dimensional errors. ``correlated`` (a time series
    along one run): the sample size is the effective one; False: the samples are independent."""
    x = np.asarray(nees, dtype=float)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return _test(dof, float("nan"), 0, 0.0, probability)
    n_eff = n / integrated_autocorrelation_time(x) if correlated else float(n)
    return _test(dof, float(x.mean()), n, n_eff, probability)


def whitened_test(w: np.ndarray, probability: float = PROBABILITY) -> NeesTest:
    """Test one run's whitened errors ``w`` (K, dof) (:func:`whiten`): the mean NEES ``|w|^2``
    against the interval for its effective sample size, ``tau`` estimated about zero
    (:func:`nees_autocorrelation_time`). Rows with a non-finite component are left out."""
    w = np.asarray(w, dtype=float)
    if w.ndim == 1:
        w = w[:, None]
    w = w[np.all(np.isfinite(w), axis=1)]
    n = int(w.shape[0])
    if n == 0:
        return _test(int(w.shape[1]), float("nan"), 0, 0.0, probability)
    nees = np.einsum("tc,tc->t", w, w)
    return _test(int(w.shape[1]), float(nees.mean()), n, n / nees_autocorrelation_time(w), probability)


def pooled_test(tests: Sequence[NeesTest], probability: float = PROBABILITY) -> NeesTest:
    """ANEES across independent runs (seeds): the sample-weighted mean of the runs' means, tested
    with the sum of their effective sample sizes. Runs without samples are left out."""
    used = [t for t in tests if t.n > 0 and np.isfinite(t.mean)]
    if not used:
        dof = tests[0].dof if tests else 1
        return _test(dof, float("nan"), 0, 0.0, probability)
    dofs = {t.dof for t in used}
    if len(dofs) != 1:
        raise NeesError(f"pooled_test needs tests of one dimension, got dofs {sorted(dofs)}")
    n = sum(t.n for t in used)
    mean = sum(t.mean * t.n for t in used) / n
    return _test(dofs.pop(), mean, n, sum(t.n_eff for t in used), probability)
