"""A prior set on disk is one build or absent, whenever its writer dies: real builds killed with SIGKILL
at random points, and writers killed on purpose between the renames of the commit."""

from __future__ import annotations

import multiprocessing
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main as prior_main
from pipeline.gis.grid import Grid
from pipeline.prior.terrain import PriorError, TerrainPrior
from pipeline.prior.write import sat_paths
from tests.pipeline.gis_helpers import REGION_TOML

REPO = REGION_TOML.parents[1]
NAMES = ("prior.tif", "prior.sat.npy", "prior.sat2.npy", "prior.qml")
# the writer's temp files, and the staging folder the CLI writes a command's outputs through
TEMP = re.compile(r"\.prior\.(tif|sat\.npy|sat2\.npy|qml)\.\d+\.[a-z0-9_]{8}(\.tif|\.npy|\.qml|\.scratch)"
                  r"|\.terrain-stage-\d+-\w+")


def _config(folder: Path, rmd: float, small: bool) -> Path:
    """The bundled region (``small``: its 200 x 200 south-west corner) with road likelihood ``rmd``."""
    text = REGION_TOML.read_text().replace('path = "', f'path = "{REGION_TOML.parent}/')
    text = text.replace("rmd = 100.0", f"rmd = {rmd}")
    if small:
        text = re.sub(r"(?m)^bounds = .*$", "bounds = [300000, 6186000, 304000, 6190000]", text)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "region.toml").write_text(text)
    return folder / "region.toml"


def _build_cmd(config: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "pipeline.cli", "-q", "build", str(config), "--out", str(out)]


ENV = os.environ | {"PYTHONPATH": str(REPO)}


def _state(out: Path, old: TerrainPrior, new: TerrainPrior, refs: dict[str, dict[str, bytes]]) -> str:
    """'old', 'new' or 'absent' for the prior at ``out``; fails on anything mixed or half-written."""
    names = set(os.listdir(out.parent))
    strays = [n for n in names - set(NAMES) if not TEMP.fullmatch(n)]
    assert strays == [], f"not ours: {strays}"
    for name in set(NAMES[1:]) & names:  # every table (and style) on disk is a whole file of one of the builds
        data = (out.parent / name).read_bytes()
        assert data in (refs["old"][name], refs["new"][name]), f"{name}: neither build's"
    if "prior.tif" not in names:
        with pytest.raises(PriorError, match="prior.tif: missing"):
            TerrainPrior.read(out)
        return "absent"
    got = TerrainPrior.read(out)  # a prior.tif on disk is always readable: one whole build
    for label, ref in (("old", old), ("new", new)):
        if np.array_equal(got.density, ref.density) and np.array_equal(got.sat, ref.sat) and np.array_equal(got.sat2, ref.sat2):
            return label
    raise AssertionError("prior.tif reads as neither build")


def _kill_rounds(tmp_path: Path, rounds: int, small: bool, seed: int) -> list[str]:
    """Rebuild over an existing prior ``rounds`` times in a subprocess: the first build runs to the end
    (its time sets the range of the random delays), the others are killed, alternately at a uniform
    random time over a whole build and a few ms after their first temp file appears. Check the state
    each time, then that the next build cleans up every temp left."""
    old_cfg, new_cfg = _config(tmp_path / "old", 100.0, small), _config(tmp_path / "new", 160.0, small)
    for cfg in (old_cfg, new_cfg):  # the two builds, in this process (no interpreter start-up)
        assert prior_main(["-q", "build", str(cfg), "--out", str(cfg.parent / "prior.tif")]) == 0
    refs = {k: {n: (tmp_path / k / n).read_bytes() for n in NAMES} for k in ("old", "new")}
    assert refs["old"]["prior.sat.npy"] != refs["new"]["prior.sat.npy"]
    old, new = (TerrainPrior.read(tmp_path / k / "prior.tif") for k in ("old", "new"))
    out = tmp_path / "out" / "prior.tif"
    out.parent.mkdir()
    rng = random.Random(seed)
    states = []
    for k in range(rounds):
        for name in NAMES:  # each round starts from the old build on disk
            shutil.copyfile(tmp_path / "old" / name, out.parent / name)
        before = set(os.listdir(out.parent))
        t0 = time.perf_counter()
        proc = subprocess.Popen(_build_cmd(new_cfg, out), env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if k == 0:
            assert proc.wait() == 0
            full = time.perf_counter() - t0
        elif k % 2:
            while proc.poll() is None and not (set(os.listdir(out.parent)) - before):
                time.sleep(0.002)
            time.sleep(rng.uniform(0.0, 0.05))
        else:
            time.sleep(rng.uniform(0.0, full))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        states.append(_state(out, old, new, refs))
    assert prior_main(["-q", "build", str(new_cfg), "--out", str(out)]) == 0
    assert sorted(os.listdir(out.parent)) == sorted(NAMES)  # the stale temps of every killed run are gone
    assert _state(out, old, new, refs) == "new"
    return states


def test_killed_builds_leave_one_build_or_none(tmp_path: Path) -> None:
    states = _kill_rounds(tmp_path, rounds=8, small=True, seed=13)
    assert states[0] == "new" and set(states) <= {"old", "new", "absent"}


@pytest.mark.slow
def test_killed_builds_leave_one_build_or_none_many(tmp_path: Path) -> None:
    states = _kill_rounds(tmp_path, rounds=33, small=False, seed=2)
    assert states[0] == "new" and set(states) <= {"old", "new", "absent"} and len(states) == 33


def _prior(seed: int) -> TerrainPrior:
    grid = Grid.from_bounds((0.0, 0.0, 400.0, 300.0), 10.0, "EPSG:32734")
    return TerrainPrior.from_array(np.random.default_rng(seed).random(grid.shape), grid, {"seed": seed})


def _write_and_die(path: str, stop: str) -> None:
    """Child: write a new prior over ``path``, exiting with os._exit(9) at ``stop``: 'unlink' (just before the
    old prior.tif is removed) or 'rename<k>' (before the k-th rename of the commit)."""
    import pathlib

    import common.atomic

    renames = iter(range(len(NAMES)))
    real_replace, real_unlink = os.replace, pathlib.Path.unlink

    def replace(src, dst):
        if stop == f"rename{next(renames)}":
            os._exit(9)
        real_replace(src, dst)

    def unlink(self, missing_ok=False):
        if stop == "unlink" and self == pathlib.Path(path):
            os._exit(9)
        real_unlink(self, missing_ok=missing_ok)

    common.atomic.os.replace = replace
    pathlib.Path.unlink = unlink
    _prior(1).write(path)
    os._exit(0)


@pytest.mark.parametrize(("stop", "want"), [("unlink", "old"), ("rename0", "absent"), ("rename1", "absent"),
                                            ("rename2", "absent"), ("rename3", "absent"), ("never", "new")])
def test_killed_between_the_renames(tmp_path: Path, stop: str, want: str) -> None:
    old_dir, new_dir, out = tmp_path / "old", tmp_path / "new", tmp_path / "out" / "prior.tif"
    old, new = _prior(0), _prior(1)
    old.write(old_dir / "prior.tif")
    new.write(new_dir / "prior.tif")
    old.write(out)
    refs = {k: {n: (tmp_path / k / n).read_bytes() for n in NAMES} for k in ("old", "new")}
    # spawn, not fork: a forked child inherits GDAL's and numba's worker threads' locks and can hang
    child = multiprocessing.get_context("spawn").Process(target=_write_and_die, args=(str(out), stop))
    child.start()
    child.join()
    assert child.exitcode == (0 if stop == "never" else 9)
    assert _state(out, TerrainPrior.read(old_dir / "prior.tif"), TerrainPrior.read(new_dir / "prior.tif"), refs) == want
    left = set(os.listdir(out.parent)) - set(NAMES)
    assert bool(left) == (stop != "never")  # the killed writer's temps ...
    new.write(out)
    assert sorted(os.listdir(out.parent)) == sorted(NAMES)  # ... are removed by the next write
    assert sat_paths(out)[0].read_bytes() == refs["new"]["prior.sat.npy"]
