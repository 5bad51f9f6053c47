"""Execute the project's notebooks headless: ``python -m notebooks.run [--fast] [names...]``.

Each notebook may tag one code cell ``parameters`` (papermill's convention). The runner inserts a
cell tagged ``injected-parameters`` right after it (replacing an earlier injected cell) that sets
``FAST`` and ``FIG_DIR``; notebooks save their figures into ``FIG_DIR`` themselves. Execution works
on an in-memory copy: the committed ``.ipynb`` files are never rewritten (``--strip`` is the one
exception, and it only removes outputs).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import nbformat
from nbclient import NotebookClient

NOTEBOOK_DIR = Path(__file__).resolve().parent
REPO_ROOT = NOTEBOOK_DIR.parent
FIG_DIR = NOTEBOOK_DIR / "figures"
KERNEL_NAME = "python3"
PARAMETERS_TAG = "parameters"
INJECTED_TAG = "injected-parameters"


def discover(names: Iterable[str] = (), folder: Path = NOTEBOOK_DIR) -> list[Path]:
    """Notebooks in `folder`, sorted; `names` (file names, stems or unique stem prefixes such as
    ``01``) selects a subset, in the order given."""
    found = sorted(folder.glob("*.ipynb"))
    selected = []
    for name in names:
        matches = [p for p in found if name in (p.name, p.stem)] or [
            p for p in found if p.stem.startswith(name)
        ]
        if len(matches) != 1:
            have = sorted(p.stem for p in found)
            raise ValueError(f"notebook name {name!r} matches {len(matches)} of {have} in {folder}")
        selected.append(matches[0])
    return selected or found


def _tags(cell: Mapping) -> list[str]:
    return list(cell.get("metadata", {}).get("tags", []))


def inject_parameters(nb: nbformat.NotebookNode, params: Mapping[str, object]) -> nbformat.NotebookNode:
    """Return a copy of `nb` with a cell assigning `params` after the ``parameters`` cell.

    Values are written with ``repr``, so they must be Python literals (bool, int, float, str, ...).
    Without a ``parameters`` cell the injected cell goes first, as papermill does.
    """
    nb = nbformat.from_dict(json.loads(json.dumps(nb)))  # deep copy, NotebookNode all the way
    cells = [c for c in nb.cells if INJECTED_TAG not in _tags(c)]
    source = "# Parameters injected by notebooks.run\n" + "".join(
        f"{name} = {value!r}\n" for name, value in params.items()
    )
    injected = nbformat.v4.new_code_cell(source, metadata={"tags": [INJECTED_TAG]})
    where = next((i + 1 for i, c in enumerate(cells) if PARAMETERS_TAG in _tags(c)), 0)
    cells.insert(where, injected)
    nb.cells = cells
    return nb


def ensure_kernel() -> str:
    """Make sure this interpreter's environment has the ``python3`` kernelspec; return its name.

    jupyter_client substitutes ``sys.executable`` for a leading ``python`` in the spec's argv, so
    the kernel runs in the same venv as the runner.
    """
    spec = Path(sys.prefix) / "share" / "jupyter" / "kernels" / KERNEL_NAME / "kernel.json"
    if not spec.is_file():
        subprocess.run(
            [sys.executable, "-m", "ipykernel", "install", "--sys-prefix", "--name", KERNEL_NAME],
            check=True,
            capture_output=True,
        )
    return KERNEL_NAME


def _kernel_env() -> dict[str, str]:
    """The runner's environment with the repository importable (notebooks run from their folder)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO_ROOT), env.get("PYTHONPATH")) if p)
    return env


def execute(
    path: Path,
    params: Mapping[str, object],
    timeout: float = 600.0,
) -> nbformat.NotebookNode:
    """Run notebook `path` with `params` injected (working directory: its folder); return the result.

    Raises nbclient's CellExecutionError (with the failing cell's traceback) when a cell fails.
    """
    nb = inject_parameters(nbformat.read(path, as_version=4), params)
    client = NotebookClient(
        nb,
        timeout=timeout,
        kernel_name=ensure_kernel(),
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute(env=_kernel_env())
    return nb


def strip_outputs(path: Path) -> bool:
    """Remove outputs and execution counts from `path` in place (atomically); True if it changed."""
    nb = nbformat.read(path, as_version=4)
    changed = False
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        changed |= bool(cell.outputs) or cell.execution_count is not None
        cell.outputs = []
        cell.execution_count = None
    if changed:
        tmp = path.with_name(f".{path.name}.tmp")
        nbformat.write(nb, tmp)
        os.replace(tmp, path)
    return changed


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m notebooks.run", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="notebook stems or file names (default: all)")
    parser.add_argument("--fast", action="store_true", help="inject FAST = True (small grids)")
    parser.add_argument("--fig-dir", type=Path, default=FIG_DIR, help=f"figure folder (default {FIG_DIR})")
    parser.add_argument("--timeout", type=float, default=600.0, help="per-cell timeout in seconds")
    parser.add_argument("--strip", action="store_true", help="only strip outputs from the notebooks")
    args = parser.parse_args(argv)

    try:
        paths = discover(args.names)
    except ValueError as err:
        parser.error(str(err))
    if args.strip:
        for path in paths:
            print(f"{path.name}: {'stripped' if strip_outputs(path) else 'clean'}")
        return 0

    fig_dir = args.fig_dir.resolve()
    fig_dir.mkdir(parents=True, exist_ok=True)
    params = {"FAST": args.fast, "FIG_DIR": str(fig_dir)}
    failed = []
    for path in paths:
        start = time.perf_counter()
        try:
            execute(path, params, timeout=args.timeout)
        except Exception as err:  # report every notebook, then fail
            failed.append(path.name)
            print(f"{path.name}: FAILED\n{err}", file=sys.stderr)
            continue
        print(f"{path.name}: ok in {time.perf_counter() - start:.1f} s")
    print(f"figures in {fig_dir}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
