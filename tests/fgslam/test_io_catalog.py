"""Catalog CSV: round trip, optional score column, clear errors on malformed files."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.errors import InputFileError
from fgslam.io import read_catalog_csv, write_catalog_csv
from reloc.measurements import RockCatalog


def test_round_trip_is_exact(tmp_path, rng):
    cat = RockCatalog(
        xy_m=rng.uniform(-50, 50, (200, 2)),
        size_m=rng.uniform(0.1, 1.5, 200),
        score=rng.uniform(0, 1, 200),
    )
    path = tmp_path / "catalog.csv"
    write_catalog_csv(path, cat)
    assert path.read_text().splitlines()[0] == "x,y,size,score"
    back = read_catalog_csv(path)
    np.testing.assert_array_equal(back.xy_m, cat.xy_m)
    np.testing.assert_array_equal(back.size_m, cat.size_m)
    np.testing.assert_array_equal(back.score, cat.score)


def test_score_optional_and_columns_in_any_order(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text("size, y ,X,extra\n0.5,2.0,1.0,foo\n1.25,-3,4.5,bar\n\n")
    cat = read_catalog_csv(path)
    np.testing.assert_array_equal(cat.xy_m, [[1.0, 2.0], [4.5, -3.0]])
    np.testing.assert_array_equal(cat.size_m, [0.5, 1.25])
    np.testing.assert_array_equal(cat.score, [1.0, 1.0])


@pytest.mark.parametrize(
    "text, needle",
    [
        ("", "line 1: empty file"),
        ("x,y,score\n1,2,0.5\n", "line 1: missing column(s) size"),
        ("x,y,size,score\n", "no rocks"),
        (
            "x,y,size,score\n1,2,0.5,0.9\n1,abc,0.5,0.9\n",
            "line 3: column 'y' is not a number: 'abc'",
        ),
        ("x,y,size,score\n1,2,nan,0.9\n", "line 2: column 'size' is nan"),
        ("x,y,size,score\n1,2,0.5\n", "line 2: 3 field(s), header has 4"),
        ("x,y,size,score\n1,2,-0.5,1\n", "line 2: size must be a positive diameter"),
        ("x,x,y,size\n1,2,3,4\n", "duplicate column(s) x"),
        ("x,y,size\n1,2,0.5\n3,4,0.5\n1.0,2.0,0.7\n", "line 4: rock at (1, 2) repeats line 2 (1 duplicate row(s)"),
    ],
)
def test_malformed_files_name_file_line_and_problem(tmp_path, text, needle):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputFileError) as exc:
        read_catalog_csv(path)
    assert str(path) in str(exc.value)
    assert needle in str(exc.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="cannot read catalog"):
        read_catalog_csv(tmp_path / "nope.csv")


def test_a_catalog_listed_twice_is_refused(tmp_path, rng):
    """Issue 17, case 8: every row duplicated (a file concatenated with itself) is no catalog."""
    cat = RockCatalog(xy_m=rng.uniform(-20, 20, (50, 2)), size_m=rng.uniform(0.2, 1.0, 50), score=np.ones(50))
    path = tmp_path / "catalog.csv"
    write_catalog_csv(path, cat)
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines + lines[1:]) + "\n")
    with pytest.raises(InputFileError, match=r"line 52: rock at .* repeats line 2 \(50 duplicate row\(s\) in all\)"):
        read_catalog_csv(path)
