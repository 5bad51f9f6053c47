"""The one CSV table reader: every way a file fails to be a CSV is a ValueError naming the file."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from common.tables import numeric_column, read_csv_table


@pytest.mark.parametrize(("content", "message"), [
    (None, "no such file"),
    (b"", "empty file; a CSV of things needs a header row"),
    (b"x,y\n1,\x002\n", "binary file: it holds NUL bytes"),
    (b"x,y\n1,\xff\xfe\n", "is not UTF-8"),
    (b'x,y\n"1,2\n', "not a readable CSV of things"),
])
def test_a_bad_file_is_an_error_naming_it(tmp_path, content, message) -> None:
    path = tmp_path / "t.csv"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(ValueError, match=message) as info:
        read_csv_table(path, "things")
    assert str(info.value).startswith(f"{path}: ")


def test_a_folder_is_an_error_naming_it(tmp_path) -> None:
    with pytest.raises(ValueError, match="is a folder, not a CSV of things"):
        read_csv_table(tmp_path, "things")


def test_numeric_column_turns_text_and_empty_cells_into_nan(tmp_path) -> None:
    path = tmp_path / "t.csv"
    path.write_text("a,b\n1.5,x\n,2\n3,\n")
    table = read_csv_table(path, "things")
    assert isinstance(table, pd.DataFrame)
    np.testing.assert_array_equal(numeric_column(table, "a"), [1.5, np.nan, 3.0])
    np.testing.assert_array_equal(numeric_column(table, "b"), [np.nan, 2.0, np.nan])
