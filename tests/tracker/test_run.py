"""tracker.run.check_method: the Python API's own checks of the batch options (the CLI refuses bad counts earlier)."""

from __future__ import annotations

import pytest

from tracker.models.motion import ConstantVelocity, Static
from tracker.run import check_method


@pytest.mark.parametrize("method, motion, sweeps, samples, seed, message", [
    ("mcmc", Static(), None, None, None, "method must be one of"),
    ("greedy", Static(), 3, None, 1, "--method greedy takes no --sweeps, --seed"),
    ("batch", ConstantVelocity(), None, None, None, "--method batch needs static targets"),
    ("batch", Static(), -1, None, None, "--sweeps must be >= 0, got -1"),
    ("batch", Static(), None, 0, None, "--samples must be >= 1, got 0"),
])
def test_bad_batch_options_are_named(method, motion, sweeps, samples, seed, message) -> None:
    with pytest.raises(ValueError, match=message):
        check_method(method, motion, sweeps, samples, seed)


def test_good_options_pass() -> None:
    check_method("batch", Static(), 0, 1, 0)
    check_method("greedy", ConstantVelocity(), None, None, None)
