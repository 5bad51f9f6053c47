"""Write outputs so a failed run leaves nothing half-written: temp file in the same folder, then rename.

Temporary names carry the writing process's id (``.<name>.<pid>.<random><suffix>``), so the next run on
a path can tell the leftovers of a killed run (owner dead) from those of a run still going (owner alive)
and remove only the former.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

SCRATCH_SUFFIX = ".scratch"
"""Suffix of the scratch folders :func:`scratch_dir` makes beside a target."""

log = logging.getLogger(__name__)


def _prefix(final: Path) -> str:
    """Start of the temporary names of ``final`` made by this process."""
    return f".{final.name}.{os.getpid()}."


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (a process of another user counts as alive)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale_temps(final: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and scratch folders of ``final`` left by runs that were killed (their
    owning process is dead); returns what was removed.

    Only names this module makes for ``final`` are considered (``.<name>.<pid>.<8 random chars>`` and
    ``final``'s suffix, or :data:`SCRATCH_SUFFIX`); a temp whose pid is alive (a concurrent run, or a
    reused pid) is kept. The pid test is local to this machine.
    """
    final = Path(final)
    suffixes = "|".join(re.escape(s) for s in {final.suffix or ".tmp", SCRATCH_SUFFIX})
    pattern = re.compile(rf"\.{re.escape(final.name)}\.(\d+)\.[a-z0-9_]{{8}}(?:{suffixes})")
    removed = []
    try:
        entries = list(os.scandir(final.parent))
    except (FileNotFoundError, NotADirectoryError):
        return removed
    for entry in entries:
        m = pattern.fullmatch(entry.name)
        if m is None or pid_alive(int(m.group(1))):
            continue
        path = Path(entry.path)
        with contextlib.suppress(FileNotFoundError):  # another run may be cleaning up too
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(path)
            else:
                path.unlink()
            removed.append(path)
            log.debug("removed %s, left by killed run %s", path, m.group(1))
    return removed


@contextlib.contextmanager
def atomic_paths(*targets: str | os.PathLike) -> Iterator[list[Path]]:
    """Yield temporary paths beside each target; rename them all into place, in order, only if the block
    succeeds. Stale temps of earlier killed runs on the same targets are removed first.

    The temporary names keep each target's suffix so drivers that look at extensions
    (GeoTIFF, GeoPackage, PNG) still work.
    """
    finals = [Path(t) for t in targets]
    temps: list[Path] = []
    try:
        for final in finals:
            final.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temps(final)
            fd, tmp = tempfile.mkstemp(prefix=_prefix(final), suffix=final.suffix or ".tmp", dir=final.parent)
            os.close(fd)
            os.unlink(tmp)  # drivers create the file themselves; keep only the unique name
            temps.append(Path(tmp))
        yield temps
        for tmp, final in zip(temps, finals, strict=True):
            os.replace(tmp, final)
    finally:
        for tmp in temps:
            if tmp.exists():
                tmp.unlink()


@contextlib.contextmanager
def scratch_dir(beside: str | os.PathLike) -> Iterator[Path]:
    """A scratch folder beside the target ``beside`` (same file system), removed on exit; named so that
    :func:`remove_stale_temps` removes it if the run is killed."""
    final = Path(beside)
    with tempfile.TemporaryDirectory(prefix=_prefix(final), suffix=SCRATCH_SUFFIX, dir=final.parent) as d:
        yield Path(d)
