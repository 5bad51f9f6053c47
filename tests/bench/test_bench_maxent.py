"""bench_maxent's scoring of Maxent's outputs against elapid's own transforms."""

import numpy as np
from elapid.models import maxent_cloglog_transform, maxent_entropy, maxent_logistic_transform
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.bench_maxent import OUTPUTS, outputs


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.1, 0.9))
def test_outputs_are_elapids_transforms(seed, tau):
    rng = np.random.default_rng(seed)
    engma = rng.normal(-8.0, 3.0, 500)
    background = np.exp(rng.normal(-8.0, 3.0, 300))
    got = outputs(np.exp(engma), background, tau)
    assert list(got) == list(OUTPUTS)
    entropy = maxent_entropy(background)
    np.testing.assert_array_equal(got["raw"], np.exp(engma))
    # elapid's 1 - exp(-ρ) cancels to ~1e-16 absolute where ρ is small; ours is expm1's
    np.testing.assert_allclose(got["cloglog"], maxent_cloglog_transform(engma, entropy), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(got["logistic"], maxent_logistic_transform(engma, entropy, tau), rtol=1e-12)


def test_a_background_value_underflowed_to_zero_counts_as_zero_mass():
    rng = np.random.default_rng(1)
    background = np.exp(rng.normal(-8.0, 3.0, 300))
    raw = np.exp(rng.normal(-8.0, 3.0, 50))
    with_zero = np.append(background, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        assert np.isnan(maxent_entropy(with_zero))  # elapid's entropy: 0 * log 0
    got, limit = outputs(raw, with_zero, 0.5), outputs(raw, np.append(background, 1e-300), 0.5)
    for name in OUTPUTS:
        assert np.all(np.isfinite(got[name]))
        np.testing.assert_allclose(got[name], limit[name], rtol=1e-12)
