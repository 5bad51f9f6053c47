"""Batches of sensor reports and of target hypotheses, as arrays (no per-object Python objects).

Positions are map coordinates in metres in the prior's CRS; times in seconds; covariances in m^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

MAX_CONDITION = 1e12
"""Largest condition number (larger / smaller eigenvalue) :func:`check_gaussians` accepts for a 2-D
covariance. Past it the float64 entries no longer fix the smaller eigenvalue: rounding the entries by
one unit in the last place moves it by ~2e-16 × the larger one, i.e. by ~2e-4 of itself at 1e12 and by
all of it near 1e16 (docs/terrace.md, "Limits")."""


def check_gaussians(means: np.ndarray, covs: np.ndarray, what: str, *, means_name: str = "means",
                    covs_name: str = "covariances") -> tuple[np.ndarray, np.ndarray]:
    """Validate (N, d) means and (N, d, d) symmetric positive-definite covariances: the tracker's one
    positive-definite check (reports, integrators, gating).

    2-D covariances must also have a condition number of at most :data:`MAX_CONDITION` (any scale,
    1e-300 to 1e300 m², is fine). Returns both as float64 arrays. Raises ``ValueError`` naming ``what``,
    the offending argument (``means_name`` or ``covs_name``) and the offending indices.
    """
    means = np.asarray(means, dtype=np.float64)
    covs = np.asarray(covs, dtype=np.float64)
    if means.ndim != 2 or covs.ndim != 3 or covs.shape != (means.shape[0], means.shape[1], means.shape[1]):
        raise ValueError(f"{what}: {means_name} must be (N, d) and {covs_name} (N, d, d); got {means.shape} "
                         f"and {covs.shape}")
    if means.shape[1] == 2:
        kernel = _flags_2d_parallel if means.shape[0] >= _PARALLEL_FROM else _flags_2d
        flags = kernel(np.ascontiguousarray(means), np.ascontiguousarray(covs))
    else:
        flags = _flags(np.ascontiguousarray(means), np.ascontiguousarray(covs))
    problems = (f"non-finite {means_name}", f"non-finite {covs_name}", f"{covs_name} not symmetric",
                f"{covs_name} not positive definite",
                f"{covs_name} too ill-conditioned (condition number above {MAX_CONDITION:.0e}: numerically "
                "singular, e.g. a correlation of ±1 to 12 digits)")
    for bit, words in enumerate(problems):
        bad = np.flatnonzero(flags == bit + 1)
        if bad.size:
            raise ValueError(f"{what}: {words} at indices {bad[:10].tolist()}")
    return means, covs


@nb.njit(cache=True)
def _cholesky_ok(a: np.ndarray, work: np.ndarray) -> bool:
    """True when the symmetric matrix ``a`` (lower triangle read) has a Cholesky factor, i.e. is
    positive definite; ``work`` (d, d) receives the factor."""
    dim = a.shape[0]
    for j in range(dim):
        s = a[j, j]
        for k in range(j):
            s -= work[j, k] * work[j, k]
        if not s > 0.0:
            return False
        work[j, j] = np.sqrt(s)
        for r in range(j + 1, dim):
            t = a[r, j]
            for k in range(j):
                t -= work[r, k] * work[j, k]
            work[r, j] = t / work[j, j]
    return True


@nb.njit(cache=True)
def _flags(means: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Per Gaussian: 0 fine, 1 non-finite mean, 2 non-finite covariance, 3 asymmetric beyond 1e-9 of
    its largest entry, 4 not positive definite (no Cholesky factor); the first that applies."""
    n, d = means.shape
    flags = np.zeros(n, dtype=np.int8)
    work = np.empty((d, d))
    for i in range(n):
        ok = True
        for r in range(d):
            ok = ok and np.isfinite(means[i, r])
        if not ok:
            flags[i] = 1
            continue
        scale = 0.0
        for r in range(d):
            for c in range(d):
                ok = ok and np.isfinite(covs[i, r, c])
                scale = max(scale, abs(covs[i, r, c]))
        if not ok:
            flags[i] = 2
            continue
        asym = 0.0
        for r in range(d):
            for c in range(r + 1, d):
                asym = max(asym, abs(covs[i, r, c] - covs[i, c, r]))
        if asym > 1e-9 * max(scale, 1e-300):
            flags[i] = 3
        elif not _cholesky_ok(covs[i], work):
            flags[i] = 4
    return flags


# 2-D Gaussians per batch from which the check runs on every core (1 M take ~55 ms on one): below
# it a parallel launch, which can wait for a descheduled worker on a loaded machine, costs more than it saves.
_PARALLEL_FROM = 200_000


@nb.njit(cache=True, inline="always")
def _flag_2d(means: np.ndarray, covs: np.ndarray, n: int) -> int:
    """The flag of 2-D Gaussian n (see :func:`_flags_2d`)."""
    a, b, c, d = covs[n, 0, 0], covs[n, 0, 1], covs[n, 1, 0], covs[n, 1, 1]
    scale = max(max(abs(a), abs(b)), max(abs(c), abs(d)))
    if not (np.isfinite(means[n, 0]) and np.isfinite(means[n, 1])):
        return 1
    if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c) and np.isfinite(d)):
        return 2
    if abs(b - c) > 1e-9 * max(scale, 1e-300):
        return 3
    if not (scale > 0.0):
        return 4
    a, d, e = a / scale, d / scale, 0.5 * (b + c) / scale
    big = 0.5 * (a + d) + np.hypot(0.5 * (a - d), e)
    small = (a * d - e * e) / big if big > 0.0 else -1.0
    if not (small > 0.0 and a > 0.0):
        return 4
    if big > MAX_CONDITION * small:
        return 5
    return 0


@nb.njit(cache=True)
def _flags_2d(means: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """:func:`_flags` for 2-D Gaussians in one pass (closed-form eigenvalues), and 5 for a condition
    number above :data:`MAX_CONDITION`.

    The entries are divided by the largest first, so neither 1e-300 nor 1e300 m² under- or overflows;
    the smaller eigenvalue is det / larger, which keeps its relative accuracy (m - hypot would cancel).
    """
    flags = np.empty(means.shape[0], dtype=np.int8)
    for n in range(means.shape[0]):
        flags[n] = _flag_2d(means, covs, n)
    return flags


@nb.njit(cache=True, parallel=True)
def _flags_2d_parallel(means: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """:func:`_flags_2d` on every core (each Gaussian's flag is independent of the others)."""
    flags = np.empty(means.shape[0], dtype=np.int8)
    for n in nb.prange(means.shape[0]):
        flags[n] = _flag_2d(means, covs, n)
    return flags


@dataclass(frozen=True)
class Reports:
    """K position reports z_k ~ N(x_j, V_k): ``means`` (K, d) metres, ``covs`` (K, d, d) m^2,
    ``times`` (K,) seconds, and, for simulated data, ``truth`` (K,) the index of the target that made each
    report (-1 when unknown).

    Every batch is validated once, when it is built (:func:`check_gaussians` on the Gaussians, then the
    times and labels; ``ValueError`` naming the offending indices), and holds float64 means, covariances
    and times and int64 labels. Consumers (the tracker, the integrators it calls) rely on that and do not
    check again; :meth:`subset` keeps the guarantee without a second pass.
    """

    means: np.ndarray
    covs: np.ndarray
    times: np.ndarray
    truth: np.ndarray

    def __post_init__(self) -> None:
        means, covs = check_gaussians(self.means, self.covs, "reports")
        n = means.shape[0]
        times = np.asarray(self.times, dtype=np.float64)
        truth = np.asarray(self.truth, dtype=np.int64)
        if times.shape != (n,) or truth.shape != (n,):
            raise ValueError(f"reports: times and truth must be ({n},), got {times.shape} and {truth.shape}")
        bad = np.flatnonzero(~np.isfinite(times))
        if bad.size:
            raise ValueError(f"reports: non-finite times at indices {bad[:10].tolist()}")
        for name, value in (("means", means), ("covs", covs), ("times", times), ("truth", truth)):
            object.__setattr__(self, name, value)  # frozen: the checked arrays replace the given ones

    @classmethod
    def create(
        cls,
        means: np.ndarray,
        covs: np.ndarray,
        times: np.ndarray | None = None,
        truth: np.ndarray | None = None,
    ) -> Reports:
        """A validated batch; ``times`` default to 0 s and ``truth`` to -1 (unknown)."""
        n = np.shape(means)[0] if np.ndim(means) else 0
        times = np.zeros(n) if times is None else times
        truth = np.full(n, -1, dtype=np.int64) if truth is None else truth
        return cls(means, covs, times, truth)

    def __len__(self) -> int:
        return self.means.shape[0]

    def subset(self, idx: np.ndarray | slice) -> Reports:
        """The reports at ``idx``: rows of a checked batch, so not checked again."""
        sub = object.__new__(Reports)
        for name in ("means", "covs", "times", "truth"):
            object.__setattr__(sub, name, getattr(self, name)[idx])
        return sub


def gaussian_product(
    a: np.ndarray, A: np.ndarray, z: np.ndarray, V: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """G(y; a, A)·G(y; z, V) = G(z; a, A+V)·G(y; b, B), batched over the leading axis.

    Returns (b, B, log G(z; a, A+V)) with B = (A⁻¹+V⁻¹)⁻¹ = A(A+V)⁻¹V and
    b = B(A⁻¹a + V⁻¹z) = V(A+V)⁻¹a + A(A+V)⁻¹z, written as sums whose terms swap when (a, A) and
    (z, V) swap, so the product is bitwise symmetric in its two factors (scores that cancel
    identical components rely on it). No inverse of A or V is needed, so either may be near-singular.
    """
    S = A + V
    S_inv = np.linalg.inv(S)
    AS = A @ S_inv
    VS = V @ S_inv
    r = z - a
    b = np.einsum("nij,nj->ni", VS, a) + np.einsum("nij,nj->ni", AS, z)
    B = 0.5 * (AS @ V + VS @ A)
    B = 0.5 * (B + B.transpose(0, 2, 1))
    d = a.shape[1]
    maha = np.einsum("ni,nij,nj->n", r, S_inv, r)
    log_g = -0.5 * (maha + np.linalg.slogdet(S)[1] + d * np.log(2 * np.pi))
    return b, B, log_g
