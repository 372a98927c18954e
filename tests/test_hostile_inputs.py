"""Nothing lost, round two (issue 66): the bad cases of a 380-case hostile probe. Folders without a manifest are
someone else's, an input is never an output, a full disk is one line, a metre is a metre, and sizes are checked
before work. Each test failed on the code before the fix.

CLI cases run ``warptan.cli.main`` in-process (exit status, the one-line message, the files afterwards); the
full-disk cases run real ``python -m warptan`` processes under ``ulimit -f``.
"""

import json
from pathlib import Path

import pytest
from test_nothing_lost import QUICK, _cli, _error_line, _snapshot

RUN_RESULTS = json.dumps({"meta": {"git_commit": "x"}, "scenarios": ["S8"], "runs": []})


# ------------------------------------------------------------------------------------------- user files
@pytest.mark.parametrize("files", [
    {"results.json": RUN_RESULTS, "results.md": "# my results", "vacation_seed2_beach.png": "a photo"},
    {"results.json": RUN_RESULTS, "README": "my analysis", "S8_seed0_track_annotated.png": "annotated",
     "compare_seed0_vs_seed1.png": "mine"},
], ids=["legacy-looking", "analysis-folder"])
def test_a_folder_without_a_manifest_is_someone_elses(capsys, tmp_path, files):
    """A folder holding a results.json but no manifest: its ``*_seed*_*.png`` were deleted and its results.json
    overwritten (exit 0). It is refused before any work, and nothing in it changes."""
    out = tmp_path / "legacy"
    out.mkdir()
    for name, text in files.items():
        (out / name).write_text(text)
    before = _snapshot(out)
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", out)
    assert status == 2
    _error_line(err, str(out), "no .warptan-run manifest", "nothing there is replaced")
    assert _snapshot(out) == before
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", out, "--check")
    assert status == 2 and "no .warptan-run manifest" in err
    assert _snapshot(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["legacy"]
