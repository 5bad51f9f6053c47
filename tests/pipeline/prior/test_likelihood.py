"""Likelihood tables against hand-written oracles: look-ups, the road form, bins, TOML round trip."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import NODATA_CODE, Grid
from pipeline.prior.likelihood import (
    BinnedLikelihood,
    CategoricalLikelihood,
    LikelihoodError,
    LikelihoodModel,
    RoadDistanceLikelihood,
    road_likelihood,
)

TABLE = {"a": 1.0, "b": 0.5, "c": 0.0, "d": 2.0}


def _oracle(codes: np.ndarray, by_code: dict[int, float], nodata: float) -> np.ndarray:
    out = np.full(codes.shape, nodata)
    for code, value in by_code.items():
        out[codes == code] = value
    return out


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spacing=st.sampled_from([1, 7, 1_000_000]))
def test_categorical_lookup_matches_cellwise_oracle(seed: int, spacing: int) -> None:
    """Dense (narrow code range) and sorted (sparse codes) look-ups give the per-cell answer."""
    rng = np.random.default_rng(seed)
    raw = rng.integers(-1, 4, size=(13, 17))
    codes = np.where(raw >= 0, raw * spacing, NODATA_CODE).astype(np.int32)
    labels = {k * spacing: name for k, name in enumerate(TABLE)}
    feature = Feature("surface", codes, "categorical", labels=labels)
    got = CategoricalLikelihood(dict(TABLE), nodata=0.7)(feature)
    expected = _oracle(codes, {k * spacing: v for k, v in enumerate(TABLE.values())}, 0.7)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(feature.codes(), np.unique(codes[codes != NODATA_CODE]))


def test_categorical_keys_may_be_codes_and_missing_category_is_named() -> None:
    feature = Feature("veg", np.array([[0, 1], [2, 1]], dtype=np.int16), "categorical", labels={0: "grass"})
    got = CategoricalLikelihood({"grass": 1.0, "1": 0.25, "2": 3.0})(feature)
    np.testing.assert_array_equal(got, [[1.0, 0.25], [3.0, 0.25]])
    with pytest.raises(LikelihoodError, match=r"veg.*'2'"):
        CategoricalLikelihood({"grass": 1.0, "1": 0.25})(feature)


@settings(max_examples=30, deadline=None)
@given(
    d=st.floats(0, 5000),
    rmd=st.floats(1, 1000),
    mv=st.floats(1e-3, 1.0),
)
def test_road_form_closed_form(d: float, rmd: float, mv: float) -> None:
    feature = Feature("road_distance", np.array([[d]]), "continuous", units="m")
    got = RoadDistanceLikelihood(rmd, mv)(feature)[0, 0]
    expected = (1 - mv) * np.exp(-(((d - rmd) / rmd) ** 2) / 2) + mv
    assert got == pytest.approx(expected, rel=1e-12)
    assert mv - 1e-12 <= got <= 1 + 1e-12


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rmd=st.floats(1, 1000), mv=st.floats(1e-3, 1.0),
       dtype=st.sampled_from([np.float32, np.float64]))
def test_road_form_is_the_formula_to_the_bit(seed: int, rmd: float, mv: float, dtype) -> None:
    """The in-place evaluation performs the formula's operations in its order: the same bits as
    (1 - mv)·exp(-0.5·z·z) + mv with z = (d - rmd)/rmd in float64, and NaN distances get nodata."""
    d = np.random.default_rng(seed).uniform(0, 3000, (9, 11)).astype(dtype)
    d[0, :3] = np.nan
    z = (d.astype(np.float64) - rmd) / rmd
    expected = (1.0 - mv) * np.exp(-0.5 * z * z) + mv
    np.testing.assert_array_equal(road_likelihood(d, rmd, mv), expected)
    expected[np.isnan(d)] = 0.4
    np.testing.assert_array_equal(RoadDistanceLikelihood(rmd, mv, nodata=0.4)(Feature("road", d, "continuous", units="m")), expected)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), order=st.permutations(["water", "road_distance", "slope"]))
def test_model_product_is_the_product_of_its_terms_to_the_bit(seed: int, order: list[str]) -> None:
    """r = 1 · r_1 · r_2 · …, multiplied in the model's order (the first factor is taken as it is)."""
    rng = np.random.default_rng(seed)
    grid = Grid.from_bounds((0, 0, 140, 100), 20, "EPSG:32734")
    stack = FeatureStack(grid)
    stack.add(Feature("water", rng.integers(-1, 2, (5, 7)).astype(np.int16), "categorical", labels={0: "dry", 1: "water"}))
    stack.add(Feature("road_distance", rng.uniform(0, 500, (5, 7)), "continuous", units="m"))
    stack.add(Feature("slope", rng.uniform(0, 30, (5, 7)).astype(np.float32), "continuous", units="deg"))
    terms = {"water": CategoricalLikelihood({"dry": 1.0, "water": 0.3}, nodata=0.9),
             "road_distance": RoadDistanceLikelihood(60.0, 0.1), "slope": BinnedLikelihood([0, 5, 15], [1.0, 0.7, 0.2])}
    model = LikelihoodModel({name: terms[name] for name in order})
    expected = np.ones(grid.shape)
    for name in order:
        expected = expected * terms[name](stack[name])
    np.testing.assert_array_equal(model.evaluate(stack), expected)


def test_road_form_rejects_bad_parameters() -> None:
    with pytest.raises(LikelihoodError, match="rmd"):
        RoadDistanceLikelihood(0.0, 0.5)
    with pytest.raises(LikelihoodError, match="mv"):
        RoadDistanceLikelihood(100.0, 0.0)


def test_binned_bins_and_nodata() -> None:
    x = np.array([[-1.0, 0.0, 4.99, 5.0], [14.0, 15.0, 99.0, np.nan]])
    got = BinnedLikelihood([0, 5, 15], [1.0, 0.5, 0.1], nodata=0.3)(Feature("slope", x, "continuous"))
    np.testing.assert_array_equal(got, [[1.0, 1.0, 1.0, 0.5], [0.5, 0.1, 0.1, 0.3]])


def test_model_product_and_toml_round_trip(tmp_path) -> None:
    grid = Grid.from_bounds((0, 0, 60, 40), 20, "EPSG:32734")
    stack = FeatureStack(grid)
    water = np.array([[0, 1, 0], [0, 0, 1]], dtype=np.int16)
    dist = np.array([[0.0, 50.0, 100.0], [200.0, 400.0, np.nan]])
    stack.add(Feature("water", water, "categorical", labels={0: "dry", 1: "water"}))
    stack.add(Feature("road_distance", dist, "continuous", units="m"))
    model = LikelihoodModel(
        {"water": CategoricalLikelihood({"dry": 1.0, "water": 0.0}), "road_distance": RoadDistanceLikelihood(100.0, 0.2)}
    )
    path = model.write_toml(tmp_path / "model.toml")
    again = LikelihoodModel.read_toml(path)
    road = 0.8 * np.exp(-(((dist - 100.0) / 100.0) ** 2) / 2) + 0.2
    expected = np.where(water == 1, 0.0, np.where(np.isnan(dist), 1.0, road))
    np.testing.assert_allclose(again.evaluate(stack), expected, rtol=1e-12)
    assert list(tmp_path.iterdir()) == [path]


def test_bad_tables_name_the_feature(tmp_path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[likelihood.slope]\ntype = "spline"\n')
    with pytest.raises(LikelihoodError, match=r"likelihood\.slope.*type"):
        LikelihoodModel.read_toml(bad)
    bad.write_text('[likelihood.water]\ntype = "categorical"\nvalues = { dry = -1.0 }\n')
    with pytest.raises(LikelihoodError, match=r"likelihood\.water"):
        LikelihoodModel.read_toml(bad)
    with pytest.raises(LikelihoodError, match="not found"):
        LikelihoodModel.read_toml(tmp_path / "missing.toml")
