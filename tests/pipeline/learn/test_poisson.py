"""The exact Hessian of the linear terms and the projected Newton fit, against independent oracles:
central differences of the analytic gradient, a numpy pass over the combinations, and L-BFGS-B."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize

from pipeline.features.stack import Feature
from pipeline.learn.estimator import PriorEstimator
from pipeline.learn.poisson import Objective, _pair_pass, fit
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.learn_synth import small_stack


@pytest.fixture(scope="module")
def fitted():
    """A fit with a categorical, a decreasing (bounded), a spline and a hybrid (kde) term."""
    stack = small_stack(90, 110)
    rows, cols = np.mgrid[0:90, 0:110]
    stack.add(Feature("elevation", 200 + 80 * np.sin(cols / 25.0) + 1.5 * rows, "continuous", "m"))
    r = np.exp(-0.5 * np.log1p(stack["road_distance"].values) - 0.5 * ((stack["elevation"].values - 250) / 60) ** 2)
    pts = TerrainPrior.from_array(r * (stack["water"].values == 0), stack.grid).sample(1500, np.random.default_rng(3))
    forms = {"road_distance": {"form": "decreasing", "scale": "log1p", "knots": 5},
             "elevation": {"form": "spline", "knots": 5, "smoothing": 3.0}}
    est = PriorEstimator(features=stack, feature_names=("water", "road_distance", "elevation"), forms=forms,
                         spatial_bandwidth=400.0, spatial_block=600.0, spatial_folds=3).fit(pts)
    obj = Objective(est.cell_stats_, est.point_stats_, est.params_, list(range(len(est.terms_))), 3.0, 1.0)
    return est, obj


def _fd_hessian(obj: Objective, x: np.ndarray, step: float = 1e-5) -> np.ndarray:
    cols = []
    for j in range(len(x)):
        e = np.zeros_like(x)
        e[j] = step
        cols.append((obj(x + e)[1] - obj(x - e)[1]) / (2 * step))
    h = np.column_stack(cols)
    return 0.5 * (h + h.T)


def test_exact_hessian_matches_central_differences_of_the_gradient(fitted) -> None:
    est, obj = fitted
    assert obj.linear
    rng = np.random.default_rng(0)
    for x in (est.theta_, est.theta_ + 0.1 * rng.standard_normal(est.theta_.shape)):
        h, fd = obj.hess(x), _fd_hessian(obj, x)
        assert np.allclose(h, fd, rtol=1e-4, atol=1e-7 * np.abs(fd).max())


def test_pair_pass_matches_numpy_accumulation(fitted) -> None:
    _, obj = fitted
    x = np.linspace(-0.2, 0.3, obj.offsets[-1])
    luts = np.concatenate([obj.params[k].cell_lut(th) for th, k in zip(obj.split(x), obj.active, strict=True)])
    log_z, shares, pairs = _pair_pass(obj._cidx, obj.cells.area, luts, obj._lut_off, obj._pair_off)
    n_t = len(obj.active)
    slot = np.where(obj._cidx >= 0, obj._lut_off[:-1] + obj._cidx, obj._lut_off[1:] - 1)
    lr = luts[slot].sum(axis=1) + np.log(obj.cells.area)
    w = np.exp(lr - lr.max())
    assert log_z == pytest.approx(np.log(w.sum()) + lr.max(), rel=1e-12)
    w /= w.sum()
    ref = np.zeros_like(shares)
    np.add.at(ref, slot.ravel(), np.repeat(w, n_t))
    assert np.allclose(shares, ref, atol=1e-13)
    for q, (a, b) in enumerate(obj._pairs):
        nb = obj._lut_off[b + 1] - obj._lut_off[b]
        table = np.zeros(obj._pair_off[q + 1] - obj._pair_off[q])
        np.add.at(table, (slot[:, a] - obj._lut_off[a]) * nb + slot[:, b] - obj._lut_off[b], w)
        assert np.allclose(pairs[obj._pair_off[q] : obj._pair_off[q + 1]], table, atol=1e-13)


def test_newton_reaches_the_lbfgsb_optimum_and_respects_the_bounds(fitted) -> None:
    est, obj = fitted
    res = fit(obj)
    assert res.success, res.message
    ref = optimize.minimize(obj, obj.x0, jac=True, method="L-BFGS-B", bounds=obj.bounds,
                            options={"maxiter": 20000, "ftol": 1e-15, "gtol": 1e-10})
    assert obj(res.x)[0] <= ref.fun + 1e-10  # at least as good as the quasi-Newton optimum
    assert np.allclose(res.x, ref.x, atol=2e-3)
    lo = np.array([-np.inf if b[0] is None else b[0] for b in obj.bounds])
    assert np.all(res.x >= lo)
    assert res.at_bound.any()  # some hinge weights sit on 0: the projection is exercised
    assert res.n_iter < 60


def test_calibration_gradient_matches_central_differences() -> None:
    """The analytic (ε, τ) gradient of the cross-fitted mixture likelihood, against differences."""
    from pipeline.learn.estimator import calibration_nll

    rng = np.random.default_rng(4)
    n, m = 300, 400
    fold = rng.integers(0, 3, n)
    per_fold = [(fold == f, rng.normal(0, 2, m), np.log(rng.uniform(100, 400, m))) for f in range(3)]
    lr = rng.normal(0, 2, n)
    w = rng.uniform(0.5, 2, n)
    w /= w.sum()
    log_u = -np.log(per_fold[0][2].size * 250.0)
    for eps, tau in ((0.05, 0.7), (0.3, 1.3), (0.0, 1.0)):
        _, g = calibration_nll(eps, tau, per_fold, lr, log_u, w)
        h = 1e-6
        fd_tau = (calibration_nll(eps, tau + h, per_fold, lr, log_u, w)[0] - calibration_nll(eps, tau - h, per_fold, lr, log_u, w)[0]) / (2 * h)
        e_hi, e_lo = eps + h, max(eps - h, 0.0)
        fd_eps = (calibration_nll(e_hi, tau, per_fold, lr, log_u, w)[0] - calibration_nll(e_lo, tau, per_fold, lr, log_u, w)[0]) / (e_hi - e_lo)
        assert g[1] == pytest.approx(fd_tau, rel=1e-5, abs=1e-8)
        assert g[0] == pytest.approx(fd_eps, rel=1e-3 if eps == 0 else 1e-5, abs=1e-7)


def test_calibration_gradient_at_zero_epsilon_is_finite_for_a_point_far_below_uniform() -> None:
    """A held-out point 800 nats below the uniform density: the one-sided ε-derivative at 0 is unbounded;
    it comes out finite, steep and towards ε > 0, with no overflow."""
    from pipeline.learn.estimator import calibration_nll

    per_fold = [(np.ones(3, bool), np.zeros(4), np.log(np.full(4, 100.0)))]
    lr = np.array([0.0, 0.0, -800.0])
    w = np.full(3, 1 / 3)
    with np.errstate(over="raise"):
        value, g = calibration_nll(0.0, 1.0, per_fold, lr, -np.log(400.0), w)
    assert np.isfinite(value) and np.isfinite(g).all() and g[0] < -1e300


@pytest.mark.parametrize("seed", range(4))
def test_fitted_epsilon_and_tau_reach_a_dense_grid_optimum_when_points_lie_far_below_uniform(seed: int) -> None:
    """A few held-out points hundreds of nats below uniform put the optimum at a small ε; fitted in ε,
    L-BFGS-B stopped at ε = 0 up to 0.4 nats per point short of it. Against a dense (ε, τ) grid."""
    from pipeline.learn.estimator import calibration_nll, fit_calibration

    rng = np.random.default_rng(seed)
    n, m = 5000, 300
    per_fold = [(np.ones(n, bool), rng.normal(0, 3, m), np.log(rng.uniform(100, 400, m)))]
    log_u = -np.log(np.exp(per_fold[0][2]).sum())
    lr = rng.normal(4, 1.0, n)
    k = int(rng.integers(1, 4))
    lr[:k] -= rng.uniform(750, 900, k)
    w = np.full(n, 1 / n)
    eps, tau = fit_calibration(per_fold, lr, log_u, w, "cv", "cv")
    grid = min(calibration_nll(e, t, per_fold, lr, log_u, w)[0]
               for e in np.logspace(-6, -1, 200) for t in np.linspace(0.05, 1.5, 146))
    assert 0 < eps < 0.01 and calibration_nll(eps, tau, per_fold, lr, log_u, w)[0] <= grid + 1e-5
    fixed = fit_calibration(per_fold, lr, log_u, w, 0.05, "cv")
    assert fixed[0] == 0.05 and fit_calibration(per_fold, lr, log_u, w, "cv", None)[1] == 1.0
