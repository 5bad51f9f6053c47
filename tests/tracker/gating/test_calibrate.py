"""Explicit calibration: it measures and writes constants only when asked; gate() never does."""

from __future__ import annotations

import numpy as np

from tracker import cli
from tracker.gating import calibrate as calibration
from tracker.gating.costmodel import DEFAULT_CONSTANTS, CostConstants
from tracker.gating.gate import gate
from tracker.gating.scene import Scene
from tracker.study.projections import predicted_choice


def test_calibrate_measures_and_writes(tmp_path):
    path = tmp_path / "sub" / "costs.json"
    c = calibration.calibrate(n=2000, rounds=1, out=path)
    assert CostConstants.read(path) == c
    assert all(v > 0 for v in c.__dict__.values())


def test_gate_uses_the_given_constants_and_never_calibrates(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    rng = np.random.default_rng(0)
    n = 400
    tm = np.hstack([rng.uniform(0, 2e4, (n, 2)), rng.uniform(-300, 300, (n, 2))])
    tc = np.tile(np.diag([100.0, 100.0, 4.0, 4.0]), (n, 1, 1))
    rm, rc, rt = rng.uniform(0, 2e4, (n, 2)), np.tile(np.eye(2) * 100.0, (n, 1, 1)), rng.uniform(0, 10, n)
    kw = dict(threshold=9.21, report_times=rt, process_noise=1.0)
    want = gate(tm, tc, rm, rc, **kw, n_projections=1, orientation="tracks")
    # projections made expensive: the model must pick one; candidates expensive: many
    few = CostConstants(b_tracks=1.0, b_reports=1.0, r_tracks=1e-7, r_reports=1e-7, c_c=1e-12)
    many = CostConstants(b_tracks=1e-12, b_reports=1e-12, r_tracks=1e-7, r_reports=1e-7, c_c=1.0)
    for c in (DEFAULT_CONSTANTS, few, many):
        got = gate(tm, tc, rm, rc, **kw, constants=c)
        assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
    assert predicted_choice(tm, tc, rm, rc, rt, threshold=9.21, process_noise=1.0, constants=few).m == 1
    assert predicted_choice(tm, tc, rm, rc, rt, threshold=9.21, process_noise=1.0, constants=many).m > 1
    assert Scene.validate(tm, tc, rm, rc, rt).moving
    assert list(tmp_path.iterdir()) == []  # nothing cached in the user's home


def test_cli_calibrate_writes_the_file(tmp_path, monkeypatch, capsys):
    fake = CostConstants(1e-7, 2e-7, 3e-7, 4e-7, 5e-7)

    def fake_calibrate(out=None):
        fake.write(out)
        return fake

    monkeypatch.setattr(calibration, "calibrate", fake_calibrate)
    path = tmp_path / "c.json"
    assert cli.main(["calibrate", "--out", str(path)]) == 0
    assert CostConstants.read(path) == fake
    assert str(path) in capsys.readouterr().out
