"""What a run says while it waits (issue 67): a first run's kernel compilation is announced while it happens (a
progress bar alone sat at ``1/600 [01:00<10:01:10]``), a cached run says nothing of it, and the phase after the bar
is named."""

import time

import pytest
from warp._src.context import Module

from warptan import cli
from warptan.progress import compile_notice


def test_a_slow_compilation_is_announced_once_and_a_cached_one_not(monkeypatch):
    calls = []

    def slow(self, *args, **kwargs):
        time.sleep(0.3)
        return True

    monkeypatch.setattr(Module, "_compile", slow)
    with compile_notice(calls.append, after_s=0.05) as state:
        Module._compile(None)
        Module._compile(None)
    assert calls[0].startswith("compiling kernels (first run only") and len(calls) == 2
    assert calls[1].startswith("kernels compiled in") and state["compiled_s"] >= 0.5
    assert Module._compile is slow  # (put back)

    monkeypatch.setattr(Module, "_compile", lambda self, *a, **k: False)
    calls.clear()
    with compile_notice(calls.append, after_s=0.05):
        Module._compile(None)
        time.sleep(0.1)
    assert calls == []


@pytest.mark.parametrize("quiet", [False, True], ids=["verbose", "quiet"])
def test_a_warm_run_names_its_phases_and_no_compilation(capsys, tmp_path, quiet):
    argv = ["run", "S8", "--duration-s", "0.2", "--particles", "16", "--no-plots", "--device", "cpu",
            "--out", str(tmp_path / "r")]
    assert cli.main(argv) == 0  # (compiles what it needs: the next run is a cached one)
    capsys.readouterr()
    assert cli.main(argv + ["--quiet"] * quiet) == 0
    out, err = capsys.readouterr()
    assert "compiling kernels" not in err
    assert ("writing results to " in err) != quiet and "writing results" not in out
