"""bench.run: discovery, merging into results.json, the markdown summary, failures recorded."""

from __future__ import annotations

import json
import sys
import types

import pytest

from bench import run as bench_run


@pytest.fixture
def bench_dir(tmp_path, monkeypatch):
    monkeypatch.setattr(bench_run, "HERE", tmp_path)
    monkeypatch.setattr(bench_run, "RESULTS_JSON", tmp_path / "results.json")
    monkeypatch.setattr(bench_run, "RESULTS_MD", tmp_path / "results.md")
    return tmp_path


def fake_bench(monkeypatch, bench_dir, name, run):
    (bench_dir / f"bench_{name}.py").write_text("")
    module = types.ModuleType(f"bench.bench_{name}")
    module.run = run
    monkeypatch.setitem(sys.modules, f"bench.bench_{name}", module)


def test_merges_and_writes_tables(bench_dir, monkeypatch):
    calls = []

    def run(quick=False):
        calls.append(quick)
        return {"size": 10 if quick else 1000, "table": [{"what": "speed", "value": "3 M/s", "ok": True}, "a note"]}

    fake_bench(monkeypatch, bench_dir, "fast", run)
    (bench_dir / "results.json").write_text(json.dumps({"benchmarks": {"older": {"date": "then", "result": {"table": []}}}}))
    assert bench_run.available() == ["fast"]
    assert bench_run.main(["--quick", "bench_fast"]) == 0
    assert calls == [True]
    results = json.loads((bench_dir / "results.json").read_text())
    assert set(results["benchmarks"]) == {"older", "fast"}
    entry = results["benchmarks"]["fast"]
    assert entry["quick"] is True and entry["result"]["size"] == 10 and entry["machine"]["cpus"] >= 1
    md = (bench_dir / "results.md").read_text()
    assert "| what | value | ok |" in md and "| speed | 3 M/s | yes |" in md and "- a note" in md
    assert not [p.name for p in bench_dir.iterdir() if p.name.startswith(".")]  # no temp files left


def test_failure_is_recorded_and_others_kept(bench_dir, monkeypatch):
    def boom(quick=False):
        raise RuntimeError("kaboom")

    fake_bench(monkeypatch, bench_dir, "good", lambda quick=False: {"table": ["fine"]})
    fake_bench(monkeypatch, bench_dir, "bad", boom)
    assert bench_run.main([]) == 1
    results = json.loads((bench_dir / "results.json").read_text())
    assert "kaboom" in results["benchmarks"]["bad"]["error"]
    assert results["benchmarks"]["good"]["result"] == {"table": ["fine"]}


def test_unknown_name(bench_dir):
    with pytest.raises(SystemExit):
        bench_run.main(["nosuch"])


def test_a_benchmark_written_by_another_run_meanwhile_is_kept(bench_dir, monkeypatch):
    def slow(quick=False):
        # another `python -m bench.run` finishes while this one runs
        (bench_dir / "results.json").write_text(json.dumps({"benchmarks": {"other": {"date": "now", "result": {"table": []}}}}))
        return {"table": ["done"]}

    fake_bench(monkeypatch, bench_dir, "mine", slow)
    (bench_dir / "results.json").write_text(json.dumps({"benchmarks": {"older": {"date": "then", "result": {"table": []}}}}))
    assert bench_run.main(["mine"]) == 0
    results = json.loads((bench_dir / "results.json").read_text())
    assert set(results["benchmarks"]) == {"other", "mine"}
