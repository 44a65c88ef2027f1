"""``fgslam bench wrong-fixes``: the shared fixes with a share made wrong, every back-end; the
table, the files, and the option checks."""

from __future__ import annotations

import json

import pytest

from fgslam.cli import main
from tests.fgslam._yard_dir import write_yard_dir


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    return write_yard_dir(tmp_path_factory.mktemp("wrongfix") / "sim", "my2020", 1, 10.0)


def test_wrong_fixes_are_refused_by_both_back_ends_and_the_table_is_written(sim_dir, tmp_path, capsys):
    out = tmp_path / "wf"
    assert main(["bench", "wrong-fixes", str(sim_dir), "--fraction", "0.3", "--offsets", "5,50", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "results.json").read_text())
    assert res["config"]["fraction"] == 0.3 and res["config"]["backends"] == ["isam2", "ekf"]
    (r,) = res["results"]
    assert r["fixes"] >= 10 and r["wrong"] == round(0.3 * r["fixes"])
    for name in ("isam2", "ekf"):
        b = r["backends"][name]
        assert b["good_accepted"] >= 0.8 * r["fixes"]  # the good fixes pass the gates ...
        assert b["wrong_accepted"] == 0  # ... fixes 5-50 m off do not
        assert b["ate_with_wrong_m"] < 1.1 * b["ate_good_m"] + 0.005
        assert b["accepted_with_wrong"] <= r["fixes"] - r["wrong"]
    assert "isam2 + reloc" in text and "ekf + reloc" in text
    assert (out / "table.md").read_text().count("\n") == 2 + 2


def test_cli_refuses_bad_options_before_any_work(sim_dir, tmp_path, capsys):
    out = tmp_path / "o"
    for args, says in ((["--fraction", "1.5"], "--fraction must be in [0, 1]"),
                       (["--offsets", "50,5"], "--offsets must be 0 < LO <= HI"),
                       (["--offsets", "5"], "--offsets must be LO,HI"),
                       (["--backends", "ekf,ukf"], "unknown back-end(s) ['ukf']"),
                       (["--duration-s", "0"], "--duration-s must be > 0")):
        assert main(["bench", "wrong-fixes", str(sim_dir), "--out", str(out), *args]) == 2
        assert says in capsys.readouterr().err
    assert main(["bench", "wrong-fixes", str(tmp_path / "missing"), "--out", str(out)]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert not out.exists()
