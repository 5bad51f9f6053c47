"""bench_outlying's held-out gain under (τ, ε) against the calibrated density written out by hand."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.bench_outlying import held_out_gain
from pipeline.gis.grid import Grid


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.3, 1.2), st.sampled_from([0.0, 0.01, 0.3]))
def test_gain_is_the_tempered_defensive_density_over_uniform(seed, tau, eps):
    rng = np.random.default_rng(seed)
    grid = Grid.from_bounds((0.0, 0.0, 600.0, 400.0), 20.0, "EPSG:32734")
    r = np.exp(rng.normal(0.0, 2.0, grid.shape))
    r[rng.random(grid.shape) < 0.2] = 0.0  # structural zeros: outside the support of the uniform part
    rows, cols = np.nonzero(r > 0)
    pick = rng.choice(len(rows), 30)
    xs, ys = grid.transform * (cols[pick] + 0.5, rows[pick] + 0.5)
    a = grid.cell_area
    by_hand = (1 - eps) * r**tau / (r**tau).sum() / a + eps / ((r > 0).sum() * a)
    expected = np.mean(np.log(by_hand[rows[pick], cols[pick]])) + np.log(r.size * a)
    got = held_out_gain(r, grid, np.column_stack([xs, ys]), tau, eps)
    assert np.isclose(got, expected, rtol=1e-6, atol=1e-6)
