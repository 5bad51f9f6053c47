"""Extreme covariances (issue 13, class 1): every scale 1e-300 … 1e12 m² and eccentricity 1 … 1e16 is
integrated in bounded memory, without hanging, by both methods, or refused by name past MAX_CONDITION.

Oracles: the closed-form limits (A → 0: the cells' values weighted by their masses, scipy's bivariate
normal CDF; A → ∞: 1/(2π√det A) times the prior's total mass of 1), the dense reference where it is
affordable, and 1/4 + arcsin(ρ)/(2π) for orthants at a corner. The sweep runs in a subprocess under
RLIMIT_AS and a timeout, so a regression that allocates gigabytes or hangs fails instead of killing the suite.
How long one such integral takes is a benchmark row (bench/bench_terrace.py, ``extreme``), not a test.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from tests.tracker.integrate.test_terraces import CELL, GRID, ROUGH
from tracker.integrate import MAX_CONDITION, integrate
from tracker.integrate.tiny import bvn_cdf

METHODS = ["scalespace", "terraces"]
X0, Y0, X1, Y1 = GRID.bounds


def cov_of(var: float, ecc: float, angle: float) -> np.ndarray:
    """Covariance with larger eigenvalue ``var`` m² and condition number ``ecc``, rotated by ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    cov = rot @ np.diag([var, var / ecc]) @ rot.T
    return 0.5 * (cov + cov.T)


def test_bvn_cdf_matches_scipy_and_the_orthant_formula() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        x, y = rng.normal(0, 2, 2)
        r = float(rng.choice([rng.uniform(-1, 1), np.sign(rng.normal()) * (1 - 10 ** rng.uniform(-8, -1))]))
        want = multivariate_normal([0, 0], [[1, r], [r, 1]], allow_singular=True).cdf([x, y])
        assert bvn_cdf(x, y, r) == pytest.approx(want, abs=1e-12)
    for r in (-0.999999, -0.3, 0.0, 0.7, 1 - 1e-12):
        assert bvn_cdf(0.0, 0.0, r) == pytest.approx(0.25 + np.arcsin(r) / (2 * np.pi), abs=1e-14)


@pytest.mark.parametrize("method", METHODS)
def test_tiny_gaussians_are_the_mass_weighted_cells(method) -> None:
    """A → 0: inside a cell r(a); on an edge the two cells' mean; at a corner the orthant masses."""
    r = ROUGH.density
    for var in (1e-300, 1e-50, 1e-16, 1e-8):
        for angle, ecc in ((0.0, 1.0), (0.6, 1e6), (2.0, 1e11)):
            cov = cov_of(var, ecc, angle)[None]
            inside = np.array([[X0 + 50.3 * CELL, Y1 - 40.7 * CELL]])
            assert integrate(ROUGH, inside, cov, method=method)[0] == pytest.approx(r[40, 50], rel=1e-12)
            edge = np.array([[X0 + 50.0 * CELL, Y1 - 40.5 * CELL]])  # the edge between columns 49 and 50
            assert integrate(ROUGH, edge, cov, method=method)[0] == pytest.approx(0.5 * (r[40, 49] + r[40, 50]), rel=1e-9)
            corner = np.array([[X0 + 50.0 * CELL, Y1 - 40.0 * CELL]])
            rho = -cov[0, 0, 1] / np.sqrt(cov[0, 0, 0]) / np.sqrt(cov[0, 1, 1])  # u-v correlation (rows grow southward)
            same = 0.25 + np.arcsin(rho) / (2 * np.pi)  # u, v both below or both above the corner
            want = same * (r[39, 49] + r[40, 50]) + (0.5 - same) * (r[39, 50] + r[40, 49])
            assert integrate(ROUGH, corner, cov, method=method)[0] == pytest.approx(want, rel=1e-9)
            assert integrate(ROUGH, corner, cov, squared=True, method=method)[0] == pytest.approx(
                same * (r[39, 49] ** 2 + r[40, 50] ** 2) + (0.5 - same) * (r[39, 50] ** 2 + r[40, 49] ** 2), rel=1e-9)


def test_condition_number_past_the_limit_is_a_named_error() -> None:
    mean = np.array([[X0 + 1000.0, Y0 + 1000.0]])
    integrate(ROUGH, mean, cov_of(1e4, MAX_CONDITION / 2, 0.7)[None])
    with pytest.raises(ValueError, match=r"integrate: covariances too ill-conditioned \(condition number above 1e\+12"):
        integrate(ROUGH, mean, cov_of(1e4, MAX_CONDITION * 4, 0.7)[None])
    a = 1e4  # the case
    with pytest.raises(ValueError, match="ill-conditioned"):
        integrate(ROUGH, mean, np.array([[[a, a * (1 - 1e-15)], [a * (1 - 1e-15), a]]]))


@pytest.mark.parametrize("method", METHODS)
def test_a_few_cell_gaussian_off_the_grid_is_not_negative(method) -> None:
    """Found by the sweep: 3 cells off the grid, the cells' four-corner masses rounded to -4e-27."""
    mean = np.array([[X0, Y0 - 0.03125 * GRID.height * CELL]])
    assert integrate(ROUGH, mean, cov_of(10.0**2.5, 100.0, 2.5)[None], method=method)[0] >= 0.0


SWEEP = """
import json, resource, sys
resource.setrlimit(resource.RLIMIT_AS, (4 * 2**30, 4 * 2**30))
import numpy as np
from hypothesis import given, settings, strategies as st
from tests.tracker.integrate.test_extreme import CELL, GRID, ROUGH, X0, Y0, cov_of
from tracker.integrate import integrate, reference_integrate
from tracker.integrate.terraces import pixel_gaussians
from tracker.types.reports import MAX_CONDITION
worst = {"err": 0.0, "cases": 0}

@settings(max_examples=int(sys.argv[1]), deadline=None, database=None)
# Half the draws in the reference's range (σ 0.3-30 cells, up to 1e4:1), so both oracles are used.
@given(lvar=st.one_of(st.floats(-300, 12), st.floats(1.6, 5.5)), lecc=st.one_of(st.floats(0, 16), st.floats(0, 4)), angle=st.floats(0, np.pi),
       fu=st.floats(-0.2, 1.2), fv=st.floats(-0.2, 1.2), method=st.sampled_from(["scalespace", "terraces"]))
def sweep(lvar, lecc, angle, fu, fv, method):
    var, ecc = 10.0 ** lvar, 10.0 ** lecc
    cov = cov_of(var, ecc, angle)[None]
    mean = np.array([[X0 + fu * GRID.width * CELL, Y0 + fv * GRID.height * CELL]])
    eig = np.linalg.eigvalsh(cov[0] / var)
    try:
        got = integrate(ROUGH, mean, cov, method=method)[0]
    except ValueError as e:
        assert "ill-conditioned" in str(e) and eig[1] > 0.5e12 * eig[0], (str(e), eig)
        return
    assert eig[1] < 2e12 * max(eig[0], 0.0) and np.isfinite(got) and got >= 0.0, (got, eig)
    sig_min = np.sqrt(var * eig[0]) / CELL  # cells
    sig_max = np.sqrt(var) / CELL
    if sig_max >= 1e4 * GRID.width:  # A → ∞: the grid sits at the Gaussian's peak
        want = 1.0 / (2 * np.pi * np.sqrt(var * var * eig[0] * eig[1]))
        assert abs(got - want) <= 1e-3 * want, (got, want)
    elif 0.3 <= sig_min and sig_max <= 30.0 and ecc <= 100.0:  # the dense reference is affordable
        want = reference_integrate(ROUGH, mean, cov)[0]
        if want > 1e-3 * ROUGH.density.mean():
            err = abs(got - want) / want
            worst["err"] = max(worst["err"], err)
            assert err <= 0.01, (got, want)
    worst["cases"] += 1

sweep()
print(json.dumps(worst))
"""


def test_sweep_scale_and_eccentricity_bounded_in_a_subprocess() -> None:
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    proc = subprocess.run([sys.executable, "-c", SWEEP, "100"], capture_output=True, text=True, timeout=240, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    worst = json.loads(proc.stdout.splitlines()[-1])
    assert worst["cases"] >= 60 and worst["err"] > 0.0, worst  # both oracles were reached
