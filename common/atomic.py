"""Write outputs so a failed run leaves nothing half-written: temp file in the same folder, then rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_paths(*targets: str | os.PathLike) -> Iterator[list[Path]]:
    """Yield temporary paths beside each target; rename them all into place only if the block succeeds.

    The temporary names keep each target's suffix so drivers that look at extensions
    (GeoTIFF, GeoPackage, PNG) still work.
    """
    finals = [Path(t) for t in targets]
    temps: list[Path] = []
    try:
        for final in finals:
            final.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(
                prefix=f".{final.stem}.", suffix=final.suffix or ".tmp", dir=final.parent
            )
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
