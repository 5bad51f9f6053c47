"""Hypotheses arrays against a plain Python list model."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tracker.types.hypotheses import Hypotheses


@settings(max_examples=25, deadline=None)
@given(ops=st.lists(st.tuples(st.booleans(), st.integers(1, 5), st.integers(0, 10**6)), min_size=1, max_size=40))
def test_append_and_fuse_match_a_list_model(ops):
    H = Hypotheses(2, capacity=1)
    model = []  # [mean, cov, log_c, count, time]
    for is_append, k, seed in ops:
        rng = np.random.default_rng(seed)
        if is_append or not model:
            m, c, lc, t = rng.normal(size=(k, 2)), np.tile(np.eye(2), (k, 1, 1)) * rng.uniform(1, 2, (k, 1, 1)), rng.normal(size=k), rng.normal(size=k)
            idx = H.append(m, c, lc, t)
            np.testing.assert_array_equal(idx, np.arange(len(model), len(model) + k))
            model += [[m[i], c[i], lc[i], 1, t[i]] for i in range(k)]
        else:
            idx = rng.choice(len(model), size=min(k, len(model)), replace=False)
            m, c, lc, t = rng.normal(size=(idx.size, 2)), np.tile(np.eye(2), (idx.size, 1, 1)), rng.normal(size=idx.size), rng.normal(size=idx.size)
            H.fuse(idx, m, c, lc, t)
            for i, q in enumerate(idx):
                model[q] = [m[i], c[i], lc[i], model[q][3] + 1, t[i]]
    assert len(H) == len(model) and H.capacity >= len(model)
    np.testing.assert_array_equal(H.means, np.array([x[0] for x in model]))
    np.testing.assert_array_equal(H.covs, np.array([x[1] for x in model]))
    np.testing.assert_array_equal(H.log_c, np.array([x[2] for x in model]))
    np.testing.assert_array_equal(H.counts, np.array([x[3] for x in model]))
    np.testing.assert_array_equal(H.times, np.array([x[4] for x in model]))
    copy = H.copy()
    np.testing.assert_array_equal(copy.counts, H.counts)
    copy.fuse(np.array([0]), H.means[:1] + 1, H.covs[:1], H.log_c[:1], H.times[:1])
    assert not np.array_equal(copy.means[0], H.means[0])  # a copy, not a view
