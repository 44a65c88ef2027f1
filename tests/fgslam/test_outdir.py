"""Output directories are written whole (issue 17, cases 6 and 7): checked and locked first,
staged, committed with a manifest; an interrupted run leaves the previous result as it was."""

from __future__ import annotations

import json
import os

import pytest

from fgslam.io.outdir import (
    COMPLETE,
    MANIFEST,
    OutputDir,
    OutputDirError,
    atomic_path,
    check_output_path,
    read_manifest,
    require_complete,
)


def _write(od: OutputDir, files: dict[str, str]) -> list:
    for name, text in files.items():
        (od.staging / name).parent.mkdir(parents=True, exist_ok=True)
        (od.staging / name).write_text(text)
    return od.commit()


def _contents(path) -> dict[str, str]:
    return {p.relative_to(path).as_posix(): p.read_text() for p in sorted(path.rglob("*")) if p.is_file()}


def test_commit_writes_the_files_and_a_complete_manifest(tmp_path):
    out = tmp_path / "cmp"
    with OutputDir(out, "compare") as od:
        assert out.is_dir() and od.staging.parent == out  # created before any work
        files = _write(od, {"table.md": "t1", "results.json": "{}", "compare.rrd": "r1"})
    assert sorted(f.name for f in files) == ["compare.rrd", "results.json", "table.md"]
    m = read_manifest(out)
    assert m["kind"] == "compare" and m["status"] == COMPLETE
    assert set(m["files"]) == {"table.md", "results.json", "compare.rrd"} and m["files"]["table.md"]["bytes"] == 2
    assert sorted(p.name for p in out.iterdir()) == ["compare.rrd", MANIFEST, "results.json", "table.md"]
    assert require_complete(out, "compare") == m


def test_a_rerun_removes_the_stale_files_and_keeps_foreign_ones(tmp_path):
    out = tmp_path / "cmp"
    with OutputDir(out, "compare") as od:
        _write(od, {"table.md": "t1", "compare.rrd": "r1", "w_xy.png": "p"})
    (out / "notes.txt").write_text("mine")  # the user's, next to a result
    with OutputDir(out, "compare") as od:  # e.g. --no-rrd, another world
        _write(od, {"table.md": "t2", "v_xy.png": "p2"})
    assert _contents(out).keys() == {"table.md", "v_xy.png", "notes.txt", MANIFEST}
    assert (out / "table.md").read_text() == "t2" and (out / "notes.txt").read_text() == "mine"


def test_an_interrupted_run_leaves_the_previous_result_untouched(tmp_path):
    out = tmp_path / "run"
    with OutputDir(out, "run") as od:
        _write(od, {"metrics.json": "old", "config.yaml": "old: 1"})
    before = _contents(out)
    with pytest.raises(KeyboardInterrupt), OutputDir(out, "run") as od:
        (od.staging / "metrics.json").write_text("new, half written")
        raise KeyboardInterrupt
    assert _contents(out) == before and not list(out.glob(".staging-*"))


def test_a_killed_runs_staging_is_removed_by_the_next_one(tmp_path):
    out = tmp_path / "run"
    with OutputDir(out, "run") as od:
        _write(od, {"metrics.json": "old"})
    (out / ".staging-999999-dead").mkdir()  # what a SIGKILL leaves
    (out / ".staging-999999-dead" / "metrics.json").write_text("partial")
    with OutputDir(out, "run") as od:
        assert not (out / ".staging-999999-dead").exists()
        _write(od, {"metrics.json": "new"})
    assert (out / "metrics.json").read_text() == "new"


def test_an_interrupted_commit_is_marked_incomplete(tmp_path):
    out = tmp_path / "sim"
    with OutputDir(out, "sim") as od:
        _write(od, {"catalog.csv": "x,y,size\n"})
    m = read_manifest(out)
    (out / MANIFEST).write_text(json.dumps({**m, "status": "writing", "files": {}, "replacing": ["catalog.csv"]}))
    with pytest.raises(OutputDirError, match="incomplete"):
        require_complete(out, "sim")
    with OutputDir(out, "sim") as od:  # a new run knows the names the interrupted one was replacing
        _write(od, {"world.yaml": "w"})
    assert not (out / "catalog.csv").exists() and require_complete(out, "sim")["status"] == COMPLETE


def test_a_second_writer_is_refused_while_the_first_holds_the_lock(tmp_path):
    out = tmp_path / "cmp"
    with OutputDir(out, "compare"), pytest.raises(OutputDirError, match="another fgslam process is writing"), \
            OutputDir(out, "compare"):
        pass
    with OutputDir(out, "compare"):  # released
        pass


def test_foreign_files_other_kinds_and_unreplaceable_outputs_are_refused(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    (home / "thesis.tex").write_text("years of work")
    with pytest.raises(OutputDirError, match=r"holds files fgslam did not write \(thesis.tex\)"), OutputDir(home, "run"):
        pass
    with OutputDir(tmp_path / "s", "sim") as od:
        _write(od, {"catalog.csv": "c"})
    with pytest.raises(OutputDirError, match="holds a `fgslam sim` output"), OutputDir(tmp_path / "s", "compare"):
        pass
    with pytest.raises(OutputDirError, match="pass --overwrite"), \
            OutputDir(tmp_path / "s", "sim", replace=False, replace_hint="pass --overwrite to replace them"):
        pass
    legacy = tmp_path / "legacy"  # a result written before manifests, or by hand: not ours to replace
    legacy.mkdir()
    (legacy / "table.md").write_text("old")
    with pytest.raises(OutputDirError, match=r"no fgslam manifest \(table.md\); .* --force"), \
            OutputDir(legacy, "compare"):
        pass
    with OutputDir(legacy, "compare", force=True) as od:  # --force: its files of this kind are replaced
        _write(od, {"results.json": "{}"})
    assert not (legacy / "table.md").exists()
    with OutputDir(home, "run", force=True) as od:  # --force beside foreign files: they are kept
        _write(od, {"metrics.json": "{}"})
    assert (home / "thesis.tex").read_text() == "years of work" and (home / "metrics.json").exists()


def test_unusable_paths_are_refused_before_anything_is_written(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputDirError, match="exists and is not a directory"):
        check_output_path(f)
    with pytest.raises(OutputDirError, match="is not a directory"):
        check_output_path(f / "sub")
    with pytest.raises(OutputDirError, match="is a directory, expected a file"):
        check_output_path(tmp_path, "--rrd", directory=False)
    if os.geteuid() != 0:  # root writes anywhere; the CLI test covers a failing mkdir for root too
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o555)
        with pytest.raises(OutputDirError, match="not writable"):
            check_output_path(ro / "out")


def test_atomic_path_replaces_a_file_only_when_the_write_succeeded(tmp_path):
    p = tmp_path / "catalog.csv"
    p.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(p) as tmp:
        tmp.write_text("new, half")
        raise RuntimeError("detector crashed")
    assert p.read_text() == "old" and [q.name for q in tmp_path.iterdir()] == ["catalog.csv"]
    with atomic_path(p) as tmp:
        tmp.write_text("new")
    assert p.read_text() == "new" and [q.name for q in tmp_path.iterdir()] == ["catalog.csv"]
