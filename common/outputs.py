"""The outputs of one command, checked against its inputs and committed together or not at all.

A command names its outputs (``--out`` and friends) and its inputs (config, layer files, prior set,
reports, ...). :func:`command_outputs` refuses, before anything runs, an output that is an input
(symlinks and hard links included), one under a regular file, a folder where a file is meant (or the
reverse), and two outputs on one path. The command then writes into a hidden staging folder beside
each output (whatever the writers put beside their file — summed-area tables, sidecars, plots — lands
there too); only when the whole command succeeds is every staged file renamed into place, in the order
it was written, after the same input check on each. A failed run removes the staging folders and the
parent folders it created; the staging folders of a killed run are removed by the next run there.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from common.atomic import pid_alive

STAGE_PREFIX = ".terrain-stage-"
"""Name prefix of staging folders: ``.terrain-stage-<pid>-<random>``."""
SHAPEFILE_SIDECARS = (".shp", ".shx", ".dbf", ".prj", ".cpg", ".qix", ".sbn", ".sbx")
"""The files a Shapefile input is made of: each is an input of a run that reads the ``.shp``."""
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM}
"""OSErrors that mean "cannot write here" when they carry no file name."""


class OutputError(ValueError):
    """An output path that cannot or must not be written (the CLIs print it as an ``error:`` line)."""


@dataclass(frozen=True)
class Output:
    """One output of a command: its ``label`` in messages (e.g. ``--out``), its ``path``, and whether
    it is a ``folder`` the command fills (else one file, plus whatever its writer puts beside it)."""

    label: str
    path: Path
    folder: bool = False


def input_files(path: str | os.PathLike) -> list[Path]:
    """The files that make up the input ``path``: itself, and for a Shapefile its sidecars."""
    p = Path(path)
    if p.suffix.lower() != ".shp":
        return [p]
    return [p.with_suffix(s) for s in SHAPEFILE_SIDECARS]


def _identity(p: Path) -> tuple[str, tuple[int, int] | None]:
    """The resolved path (symlinks followed) and, for an existing file, its (device, inode)."""
    try:
        st = p.stat()
        ino = (st.st_dev, st.st_ino)
    except OSError:
        ino = None
    return os.path.realpath(p), ino


class _Inputs:
    """The input files of a run, to refuse an output that would replace one."""

    def __init__(self, inputs: Mapping[str, Iterable[Path]]) -> None:
        self.by_path: dict[str, str] = {}
        self.by_inode: dict[tuple[int, int], str] = {}
        for label, paths in inputs.items():
            for p in paths:
                real, ino = _identity(Path(p))
                self.by_path.setdefault(real, label)
                if ino is not None:
                    self.by_inode.setdefault(ino, label)

    def which(self, p: Path) -> str | None:
        """The label of the input that ``p`` is (same resolved path or same file), else None."""
        real, ino = _identity(p)
        return self.by_path.get(real) or (self.by_inode.get(ino) if ino is not None else None)


def _check(outputs: list[Output], inputs: _Inputs) -> None:
    seen: dict[str, str] = {}
    for o in outputs:
        label = inputs.which(o.path)
        if label is not None:
            raise OutputError(f"{o.label} {o.path}: is an input of this run ({label}); "
                              "inputs are never overwritten, choose another path")
        real = os.path.realpath(o.path)
        if real in seen:
            raise OutputError(f"{o.label} {o.path}: same path as {seen[real]}; give each output its own path")
        seen[real] = o.label
        for parent in o.path.absolute().parents:
            if parent.exists() or parent.is_symlink():
                if not parent.is_dir():
                    raise OutputError(f"{o.label} {o.path}: {parent} is not a folder")
                break
        if o.folder and o.path.exists() and not o.path.is_dir():
            raise OutputError(f"{o.label} {o.path}: exists and is not a folder; give a folder path")
        if not o.folder and o.path.is_dir():
            raise OutputError(f"{o.label} {o.path}: is a folder; give a file path (inside it, say)")


    return True


def remove_stale_stages(folder: Path) -> None:
    """Remove the staging folders in ``folder`` left by killed runs (whose process is gone)."""
    for d in folder.glob(STAGE_PREFIX + "*"):
        pid = d.name[len(STAGE_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


def _make_parents(folder: Path, created: list[Path]) -> None:
    missing = [p for p in [folder, *folder.parents] if not p.exists()]
    for p in reversed(missing):
        p.mkdir()
        created.append(p)


class Staging:
    """Where a command writes its outputs until they are committed: :meth:`path` of each output."""

    def __init__(self, outputs: list[Output], inputs: _Inputs) -> None:
        self.outputs, self.inputs = outputs, inputs
        self.stages: dict[Path, Path] = {}  # final parent folder -> its staging folder
        self.created: list[Path] = []  # parent folders this run made, outermost first
        self.staged: dict[str, Path] = {}

    def open(self) -> None:
        for o in self.outputs:
            parent = o.path.absolute().parent
            if parent not in self.stages:
                _make_parents(parent, self.created)
                remove_stale_stages(parent)
                self.stages[parent] = Path(tempfile.mkdtemp(prefix=f"{STAGE_PREFIX}{os.getpid()}-", dir=parent))
            staged = self.stages[parent] / o.path.name
            if o.folder:
                staged.mkdir()
            self.staged[o.label] = staged

    def path(self, label: str) -> Path:
        """The staged path to write output ``label`` to."""
        return self.staged[label]

    def final(self, staged: str | os.PathLike) -> Path:
        """The final path of a staged path (for messages: what the command wrote)."""
        p = Path(staged)
        for parent, stage in self.stages.items():
            if p == stage or stage in p.parents:
                return parent / p.relative_to(stage)
        return p

    def named(self, exc: OSError) -> OutputError | None:
        """``exc`` as an error naming the output it hit, or None when it is not about writing outputs."""
        reason = exc.strerror or str(exc)
        if exc.filename is not None:
            final = self.final(exc.filename)
            if final != Path(exc.filename):
                return OutputError(f"{final}: cannot write ({reason})")
        if exc.errno in _WRITE_ERRNOS and exc.filename is None:
            names = ", ".join(f"{o.label} {o.path}" for o in self.outputs)
            return OutputError(f"cannot write {names} ({reason})")
        return None

    def commit(self) -> None:
        """Rename every staged file into place, oldest first (a writer's last file is committed last), after
        removing the files they replace."""
        moves: list[tuple[int, Path, Path]] = []
        for parent, stage in self.stages.items():
            for src in stage.rglob("*"):
                if src.is_dir() and not src.is_symlink():
                    continue
                dest = parent / src.relative_to(stage)
                label = self.inputs.which(dest)
                if label is not None:
                    raise OutputError(f"{dest}: would replace an input of this run ({label}); choose another output path")
                if dest.is_dir():
                    raise OutputError(f"{dest}: is a folder; cannot write a file there")
                moves.append((src.lstat().st_mtime_ns, src, dest))
        moves.sort(key=lambda m: (m[0], str(m[1])))
        # Old outputs go first, the last-committed first: a kill during the renames then leaves each
        # output new or absent, never an old file beside new ones (a prior.tif beside newer tables).
        for _, _, dest in reversed(moves):
            dest.unlink(missing_ok=True)
        for _, src, dest in moves:
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dest)

    def close(self, committed: bool) -> None:
        for stage in self.stages.values():
            shutil.rmtree(stage, ignore_errors=True)
        if not committed:
            for p in reversed(self.created):
                with contextlib.suppress(OSError):  # not empty: something else wrote there meanwhile
                    p.rmdir()


@contextlib.contextmanager
def command_outputs(outputs: Iterable[Output | None], inputs: Mapping[str, Iterable[Path]]) -> Iterator[Staging]:
    """Check ``outputs`` against ``inputs`` (label -> files; see the module doc), yield the
    :class:`Staging` to write them through, and commit them all when the block succeeds. Raises
    :class:`OutputError` naming the output; an OSError about a staged file is re-raised as one."""
    outs = [o for o in outputs if o is not None]
    ins = _Inputs(inputs)
    _check(outs, ins)
    staging = Staging(outs, ins)
    committed = False
    try:
        staging.open()
        try:
            yield staging
        except OSError as exc:
            named = staging.named(exc)
            if named is None:
                raise
            raise named from exc
        staging.commit()
        committed = True
    finally:
        staging.close(committed)
