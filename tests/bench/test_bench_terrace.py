"""bench_terrace in quick mode: it runs, measures both methods against the reference, draws its figure."""

from __future__ import annotations

from bench import bench_terrace


def test_quick_run(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(bench_terrace, "FIGURE", tmp_path / "figures" / "terrace_speed.png")
    result = bench_terrace.run(quick=True)
    assert (tmp_path / "figures" / "terrace_speed.png").stat().st_size > 0
    assert [p["spread_cells"] for p in result["per_spread"]] == list(bench_terrace.SPREADS)
    for p in result["per_spread"]:
        assert p["scalespace_max_rel_err"] <= 0.01 and p["terrace_max_rel_err"] <= 0.01
        assert p["scalespace_per_s"] > 0 and p["reference_per_s"] > 0 and p["mc_per_s"] > 0
    assert result["mixed_per_s"] > 0 and result["pyramid_levels"] > 0
    assert "integrals/s" in result["table"][-1]
