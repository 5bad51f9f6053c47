"""Every notebook in notebooks/ runs in fast mode and is committed without outputs; notebooks.run works.

A notebook too slow for the default suite even in fast mode sets, in its metadata,
``"notebooks_run": {"fast_test": false}``; its execution test is then marked slow. A notebook on real data
names the fixture of its folder (``"notebooks_run": {"real_data": "swellendam"}``): without the data its
execution test skips with the reason, and fails when CI=true.
"""

from __future__ import annotations

import ast
import hashlib
import sys
from pathlib import Path

import matplotlib.image as mpimg
import nbformat
import pytest
from nbclient.exceptions import CellExecutionError

from notebooks import run

NOTEBOOKS = run.discover()


def _is_slow(path: Path) -> bool:
    meta = nbformat.read(path, as_version=4).metadata.get("notebooks_run", {})
    return meta.get("fast_test", True) is False


def _params(nb: nbformat.NotebookNode) -> list[nbformat.NotebookNode]:
    return [c for c in nb.cells if run.PARAMETERS_TAG in c.get("metadata", {}).get("tags", [])]


@pytest.mark.parametrize(
    "path",
    [pytest.param(p, id=p.stem, marks=[pytest.mark.slow] if _is_slow(p) else []) for p in NOTEBOOKS],
)
def test_notebook_runs_in_fast_mode(path: Path, tmp_path: Path, request: pytest.FixtureRequest):
    needs = nbformat.read(path, as_version=4).metadata.get("notebooks_run", {}).get("real_data")
    if needs:
        request.getfixturevalue(needs)  # skips without the real data (fails when CI=true): tests/conftest.py
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    run.execute(path, {"FAST": True, "FIG_DIR": str(tmp_path)}, timeout=300)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before, "committed notebook was rewritten"
    figures = sorted(tmp_path.glob("*.png"))
    assert figures, f"{path.name} saved no figure into FIG_DIR"
    for fig in figures:
        image = mpimg.imread(fig)
        assert image.shape[0] > 50 and image.shape[1] > 50, fig.name


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_committed_notebook_has_no_outputs(path: Path):
    nb = nbformat.read(path, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name} cell {i} has outputs"
            assert cell.execution_count is None, f"{path.name} cell {i} has an execution count"
        assert run.INJECTED_TAG not in cell.get("metadata", {}).get("tags", []), path.name


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_declares_fast_and_fig_dir(path: Path):
    cells = _params(nbformat.read(path, as_version=4))
    assert len(cells) == 1, f"{path.name} needs exactly one cell tagged 'parameters'"
    assigned = {
        target.id
        for node in ast.walk(ast.parse(cells[0].source))
        if isinstance(node, ast.Assign)
        for target in node.targets
        if isinstance(target, ast.Name)
    }
    assert {"FAST", "FIG_DIR"} <= assigned, f"{path.name} parameters cell assigns {assigned}"


# --- the runner itself ----------------------------------------------------------------------


def _toy_notebook(with_parameters: bool = True) -> nbformat.NotebookNode:
    cells = [nbformat.v4.new_code_cell("A = 1\nB = 'x'")]
    if with_parameters:
        cells[0].metadata["tags"] = ["parameters"]
    cells.append(nbformat.v4.new_code_cell("C = A + 1"))
    return nbformat.v4.new_notebook(cells=cells)


def _exec_cells(nb: nbformat.NotebookNode) -> dict:
    namespace: dict = {}
    for cell in nb.cells:
        exec(cell.source, namespace)  # noqa: S102 - plain Python as the independent oracle
    return namespace


def test_inject_parameters_overrides_after_the_parameters_cell():
    nb = _toy_notebook()
    original = nbformat.writes(nb)
    out = run.inject_parameters(nb, {"A": 5, "FIG_DIR": "/tmp/f"})
    assert nbformat.writes(nb) == original, "input notebook mutated"
    assert [run.INJECTED_TAG in c.metadata.get("tags", []) for c in out.cells] == [False, True, False]
    ns = _exec_cells(out)
    assert (ns["A"], ns["B"], ns["C"], ns["FIG_DIR"]) == (5, "x", 6, "/tmp/f")
    # Injecting again replaces the earlier injected cell instead of stacking a second one.
    again = run.inject_parameters(out, {"A": 7})
    assert len(again.cells) == 3
    assert _exec_cells(again)["C"] == 8
    assert "FIG_DIR" not in _exec_cells(again)


def test_inject_parameters_without_parameters_cell_goes_first():
    out = run.inject_parameters(_toy_notebook(with_parameters=False), {"A": 5})
    assert run.INJECTED_TAG in out.cells[0].metadata["tags"]
    assert _exec_cells(out)["A"] == 1  # the notebook's own assignment runs later and wins


def _write_toy(folder: Path, name: str, nb: nbformat.NotebookNode) -> Path:
    path = folder / name
    nbformat.write(nb, path)
    return path


def test_discover_selects_by_name_stem_and_unique_prefix(tmp_path: Path):
    a = _write_toy(tmp_path, "01_alpha.ipynb", _toy_notebook())
    b = _write_toy(tmp_path, "02_beta.ipynb", _toy_notebook())
    c = _write_toy(tmp_path, "021_gamma.ipynb", _toy_notebook())
    assert run.discover(folder=tmp_path) == [a, c, b]  # sorted by file name
    assert run.discover(["02_beta", "01"], folder=tmp_path) == [b, a]
    assert run.discover(["01_alpha.ipynb"], folder=tmp_path) == [a]
    with pytest.raises(ValueError, match="'02'"):
        run.discover(["02"], folder=tmp_path)  # 02_beta and 021_gamma
    with pytest.raises(ValueError, match="'zz'"):
        run.discover(["zz"], folder=tmp_path)


def test_strip_outputs(tmp_path: Path):
    nb = _toy_notebook()
    nb.cells[1].outputs = [nbformat.v4.new_output("stream", name="stdout", text="2\n")]
    nb.cells[1].execution_count = 3
    path = _write_toy(tmp_path, "dirty.ipynb", nb)
    assert run.strip_outputs(path) is True
    clean = nbformat.read(path, as_version=4)
    assert all(c.outputs == [] and c.execution_count is None for c in clean.cells)
    assert [c.source for c in clean.cells] == [c.source for c in nb.cells]
    assert run.strip_outputs(path) is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dirty.ipynb"]


def test_kernel_is_this_interpreter_and_sees_the_repo(tmp_path: Path):
    nb = nbformat.v4.new_notebook(
        cells=[
            nbformat.v4.new_code_cell("import sys, tracker\nprint(sys.executable)\nprint(tracker.__file__)")
        ]
    )
    path = _write_toy(tmp_path, "probe.ipynb", nb)
    out = run.execute(path, {})
    executable, tracker_file = out.cells[-1].outputs[0]["text"].split()
    assert Path(executable).resolve() == Path(sys.executable).resolve()
    assert Path(tracker_file).resolve().parent == run.REPO_ROOT / "tracker"


def test_failing_cell_raises_with_its_message(tmp_path: Path):
    path = _write_toy(
        tmp_path, "broken.ipynb", nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell("1 / 0")])
    )
    with pytest.raises(CellExecutionError, match="ZeroDivisionError"):
        run.execute(path, {})
