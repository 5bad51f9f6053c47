"""The argparse number types of common.cli: the bounds they enforce, against Python's own comparisons."""

from __future__ import annotations

import argparse
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.cli import count, number


@given(st.floats(allow_nan=True, allow_infinity=True), st.booleans())
def test_number_accepts_exactly_the_finite_values_in_its_range(x: float, strict: bool) -> None:
    parse = number(0, 1, strict=strict)
    inside = math.isfinite(x) and ((0 < x < 1) if strict else (0 <= x <= 1))
    if inside:
        assert parse(repr(x)) == x
    else:
        with pytest.raises(argparse.ArgumentTypeError, match=r"must be a finite number (>|>=) 0 and (<|<=) 1, got"):
            parse(repr(x))


@pytest.mark.parametrize("text", ["nan", "-inf", "inf", "abc", ""])
def test_unbounded_number_still_needs_a_finite_value(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=f"must be a finite number, got {text!r}"):
        number()(text)
    assert number()("-2.5") == -2.5


@given(st.integers(-10, 10))
def test_count_accepts_integers_from_its_minimum(n: int) -> None:
    if n >= 2:
        assert count(2)(str(n)) == n
    else:
        with pytest.raises(argparse.ArgumentTypeError, match=f"must be an integer >= 2, got '{n}'"):
            count(2)(str(n))
    with pytest.raises(argparse.ArgumentTypeError):
        count(2)("2.5")
