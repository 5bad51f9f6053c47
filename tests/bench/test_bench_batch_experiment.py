"""bench_batch_experiment.replicate: blocks of fresh seeds, each summarised on its own data sets."""

from bench.bench_batch_experiment import replicate


def test_replicate_summarises_each_block_and_all_of_them():
    out = replicate(blocks=2, per_block=2, base_seed=50, taus="-4:-3:1", workers=1)
    assert [out[k]["seeds"] for k in ("block 1", "block 2", "all")] == [[50, 51], [52, 53], [50, 53]]
    for cells in out.values():
        assert set(cells["best_tau"]) == {"TT", "TT posterior"} and all(t in (-4.0, -3.0) for t in cells["best_tau"].values())
        assert all(0.0 <= cells[k] <= 1.0 for k in cells if k.startswith("prob_better"))
        assert len(cells["mean_nd_abs_error_best_tau"]) == 2  # posterior, greedy
