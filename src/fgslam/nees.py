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
autocorrelation time of the NEES series (Sokal's automatic window, ``M >= 5 tau(M)``). Runs are
combined (ANEES across seeds) by pooling: the mean of all samples, tested with the sum of the
runs' effective sizes.
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


def integrated_autocorrelation_time(x: np.ndarray) -> float:
    """Integrated autocorrelation time ``tau = 1 + 2 sum_k rho_k`` of a 1D series (>= 1), with
    Sokal's automatic window (the smallest ``M`` with ``M >= 5 tau(M)``); 1 for fewer than 4 samples
    or a constant series."""
    x = np.asarray(x, dtype=float)
    n = x.size
    if n < 4:
        return 1.0
    d = x - x.mean()
    var = float(d @ d)
    if var <= 0.0:
        return 1.0
    m = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(d, m)
    acf = np.fft.irfft(f * np.conj(f), m)[:n] / var
    taus = 2.0 * np.cumsum(acf) - 1.0  # tau(M) = 1 + 2 sum_{k=1..M} rho_k
    window = np.flatnonzero(np.arange(n) >= SOKAL_WINDOW_C * taus)
    tau = taus[window[0]] if window.size else taus[-1]
    return float(min(max(tau, 1.0), n))


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
