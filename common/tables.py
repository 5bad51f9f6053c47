"""The one reader of CSV tables given on the command line (reports, true targets, past targets and
their weights): every way a file can fail to be a CSV table becomes a ``ValueError`` naming it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd


def read_csv_table(path: str | Path, what: str) -> pd.DataFrame:
    """A CSV file as a table; ``ValueError`` naming the file (``what`` it should hold) when it is missing,
    a folder, empty, binary (a NUL byte in its first 8 KiB, or not UTF-8) or not CSV."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            binary = b"\0" in f.read(8192)
        if binary:
            raise ValueError(f"{path}: not a text CSV of {what} (binary file: it holds NUL bytes)")
        return pd.read_csv(path)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, not a CSV of {what}") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text CSV of {what} (byte {exc.start} is not UTF-8; binary file?)") from None
    except pd.errors.EmptyDataError:
        raise ValueError(f"{path}: empty file; a CSV of {what} needs a header row") from None
    except pd.errors.ParserError as exc:
        raise ValueError(f"{path}: not a readable CSV of {what} ({str(exc).strip()})") from None


def numeric_column(table: pd.DataFrame, column: str) -> np.ndarray:
    """``column`` of ``table`` as float64, text and empty cells as NaN (for the caller to name the rows)."""
    return pd.to_numeric(table[column], errors="coerce").to_numpy(dtype=np.float64)
