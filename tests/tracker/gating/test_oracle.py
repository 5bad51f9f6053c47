"""Independent brute-force oracle and random scenes for the gating tests (dense numpy linear
algebra over every track/report pair; no code shared with tracker.gating.gate)."""

from __future__ import annotations

import numpy as np


def random_covs(rng: np.random.Generator, n: int, dim: int, sigma_lo: float, sigma_hi: float,
                cond: float = 1.0) -> np.ndarray:
    """Random orientations; std devs log-uniform in [lo, hi]; variances of the minor axes
    shrunk by up to 1/cond (cond = 1e6: near-singular)."""
    q, _ = np.linalg.qr(rng.normal(size=(n, dim, dim)))
    sig = np.exp(rng.uniform(np.log(sigma_lo), np.log(sigma_hi), (n, dim)))
    shrink = np.exp(rng.uniform(-np.log(cond), 0.0, (n, dim)))
    shrink[:, 0] = 1.0
    ev = sig**2 * shrink
    c = np.einsum("nij,nj,nkj->nik", q, ev, q)
    return 0.5 * (c + c.transpose(0, 2, 1))


def brute_force(tm, tc, rm, rc, *, gamma=None, min_score=None, report_times=None,
                track_times=0.0, q=0.0):
    """d^2 (N, M) and the pass mask, projecting each track to each report's time with F P F^T + Q."""
    nt, nr, dim = tm.shape[0], rm.shape[0], rm.shape[1]
    if tm.shape[1] == 2 * dim:
        dt = np.asarray(report_times)[None, :] - np.broadcast_to(track_times, (nt,))[:, None]
        qn = np.broadcast_to(np.asarray(q, float), (nt,))[:, None]
        eye = np.eye(dim)
        f = np.zeros((nt, nr, 2 * dim, 2 * dim))
        f[..., :dim, :dim] = eye
        f[..., dim:, dim:] = eye
        f[..., :dim, dim:] = dt[..., None, None] * eye
        x = np.einsum("ijab,ib->ija", f, tm)
        p = np.einsum("ijab,ibc,ijdc->ijad", f, tc, f)
        a = np.abs(dt)
        qq = np.zeros_like(p)
        qq[..., :dim, :dim] = (qn * a**3 / 3)[..., None, None] * eye
        qq[..., :dim, dim:] = (qn * a**2 / 2)[..., None, None] * eye
        qq[..., dim:, :dim] = (qn * a**2 / 2)[..., None, None] * eye
        qq[..., dim:, dim:] = (qn * a)[..., None, None] * eye
        p = p + qq
        pos, pcov = x[..., :dim], p[..., :dim, :dim]
    else:
        pos = np.broadcast_to(tm[:, None, :], (nt, nr, dim))
        pcov = np.broadcast_to(tc[:, None], (nt, nr, dim, dim))
    v = pcov + rc[None]
    dx = rm[None] - pos
    d2 = np.einsum("ija,ija->ij", dx, np.linalg.solve(v, dx[..., None])[..., 0])
    if gamma is not None:
        limit = np.full(d2.shape, gamma)
    else:
        _, logdet = np.linalg.slogdet(v)
        limit = -2 * np.log(min_score) - dim * np.log(2 * np.pi) - logdet
    return d2, limit


def assert_same_pairs(t_idx, r_idx, d2, limit, rtol=1e-7):
    """Gate output equals the brute-force pass set, except pairs within rtol of the threshold."""
    nt, nr = d2.shape
    got = np.zeros((nt, nr), bool)
    got[t_idx, r_idx] = True
    want = d2 <= limit
    border = np.abs(d2 - limit) <= rtol * np.maximum(np.abs(limit), 1.0)
    missing = want & ~got & ~border
    extra = got & ~want & ~border
    assert not missing.any(), f"false negatives at {np.argwhere(missing)[:5]}"
    assert not extra.any(), f"false positives at {np.argwhere(extra)[:5]}"
    key = t_idx * nr + r_idx
    assert np.all(np.diff(key) > 0), "pairs not sorted by (track, report) or duplicated"


def test_oracle_against_closed_forms():
    """The oracle itself: identity covariances give d^2 = |dX|^2 / 2; a CV track moved by dt
    with q gives position variance 1 + dt^2 + q dt^3 / 3 per axis (unit P)."""
    rng = np.random.default_rng(0)
    tm, rm = rng.normal(size=(3, 2)), rng.normal(size=(4, 2))
    eye = np.tile(np.eye(2), (4, 1, 1))
    d2, limit = brute_force(tm, eye[:3], rm, eye, gamma=1.0)
    np.testing.assert_allclose(d2, ((rm[None] - tm[:, None]) ** 2).sum(-1) / 2)
    assert np.all(limit == 1.0)
    state = np.array([[0.0, 0.0, 2.0, -1.0]])
    dt, q = 3.0, 0.5
    report_cov = 1e-300 * np.eye(2)[None]  # a point report
    d2, _ = brute_force(state, np.eye(4)[None], np.array([[6.0, -2.0]]), report_cov, gamma=1.0,
                        report_times=np.array([dt]), track_times=0.0, q=q)
    np.testing.assert_allclose(d2[0, 0], 1.0 / (1 + dt**2 + q * dt**3 / 3))
