"""atomic_paths: all targets or none, and the stale temps of killed runs (owner dead) removed by the next
run on the same path while those of live runs and anything not ours stay."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from common.atomic import atomic_paths, remove_stale_temps, scratch_dir


def _dead_pid() -> int:
    """The pid of a process that has exited and been reaped."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_commits_all_targets_or_none(tmp_path: Path) -> None:
    a, b = tmp_path / "a.json", tmp_path / "sub" / "b.md"
    with atomic_paths(a, b) as (ta, tb):
        assert ta.parent == a.parent and tb.parent == b.parent and ta.suffix == ".json" and tb.suffix == ".md"
        assert ta.name.startswith(f".a.json.{os.getpid()}.")
        ta.write_text("1")
        tb.write_text("2")
    assert a.read_text() == "1" and b.read_text() == "2"
    with pytest.raises(RuntimeError), atomic_paths(a, b) as (ta, tb):
        ta.write_text("new")
        raise RuntimeError
    assert a.read_text() == "1" and sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "sub"]


def test_stale_temps_of_dead_runs_are_removed(tmp_path: Path) -> None:
    dead, alive = _dead_pid(), os.getppid()
    stale = [tmp_path / f".prior.tif.{dead}.ab_c12xy.tif", tmp_path / f".prior.tif.{dead}.zzzzzzzz.scratch"]
    stale[0].write_bytes(b"half a GeoTIFF")
    stale[1].mkdir()
    (stale[1] / "density.tif").write_bytes(b"x")
    kept = [
        tmp_path / f".prior.tif.{alive}.ab_c12xy.tif",  # a concurrent run
        tmp_path / f".prior.tif.{os.getpid()}.ab_c12xy.tif",  # this process
        tmp_path / f".prior.sat.npy.{dead}.ab_c12xy.npy",  # another target's: removed by its own run
        tmp_path / f".prior.tif.{dead}.ab_c12xy.npy",  # not a suffix we give this target
        tmp_path / f".prior.tif.{dead}.abc.tif",  # not our random part
        tmp_path / f"prior.tif.{dead}.ab_c12xy.tif",  # not hidden
        tmp_path / ".prior.abc12xyz.tif",  # the old names, without a pid: owner unknown
        tmp_path / "prior.tif",
    ]
    for p in kept:
        p.write_bytes(b"keep")
    with atomic_paths(tmp_path / "prior.tif") as (tmp,):
        assert not any(p.exists() for p in stale)
        tmp.write_bytes(b"new")
    assert all(p.exists() for p in kept[:-1]) and (tmp_path / "prior.tif").read_bytes() == b"new"
    assert remove_stale_temps(tmp_path / "prior.sat.npy") == [kept[2]]
    assert remove_stale_temps(tmp_path / "missing" / "x.tif") == []


def test_temps_of_a_killed_run_are_removed_by_the_next(tmp_path: Path) -> None:
    """A real run killed inside atomic_paths (os._exit) leaves its temps and scratch folder; the next run removes them."""
    target = tmp_path / "out.tif"
    code = (
        "import os, sys; from common.atomic import atomic_paths, scratch_dir\n"
        f"with atomic_paths({str(target)!r}, {str(tmp_path / 'out.md')!r}) as temps, scratch_dir({str(target)!r}) as s:\n"
        "    [t.write_bytes(b'half') for t in temps]; (s / 'x').write_bytes(b'x'); os._exit(9)\n"
    )
    env = os.environ | {"PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    assert subprocess.run([sys.executable, "-c", code], env=env).returncode == 9
    left = sorted(p.name for p in tmp_path.iterdir())
    assert len(left) == 3 and all(n.startswith((".out.tif.", ".out.md.")) for n in left)
    with atomic_paths(target, tmp_path / "out.md") as temps:
        for t in temps:
            t.write_bytes(b"done")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.md", "out.tif"]


def test_scratch_dir_is_removed_on_exit(tmp_path: Path) -> None:
    with scratch_dir(tmp_path / "prior.tif") as d:
        assert d.is_dir() and d.parent == tmp_path and d.name.endswith(".scratch")
        (d / "f").write_bytes(b"x")
    assert list(tmp_path.iterdir()) == []
