"""Every example in README and docs runs as written (issue 67): the Python blocks of each page in one interpreter, in
order (a later block may use an earlier one's names), and each command line of its shell blocks, from an empty folder
that holds only the repository's ``campaigns/``. Skipped, and only these: a line marked ``# yours`` (it needs the
reader's own file: a DEM, a flight log, a cluster), a line that needs a GPU (``--device cuda``), and ``pytest`` (this
suite). ``pip install … &&`` in front of a command is dropped: the test runs in the installed environment. Synopses are
``text`` blocks and are not run."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MD_BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
RST_BLOCK = re.compile(r"^\.\. code-block:: (\w+)\n\n((?:(?:    .*)?\n)+)", re.M)
PAGES = ["README.md", "docs/user-guide.md", "docs/getting-started.rst"]


def blocks(page: str, lang: str) -> list[str]:
    text = (ROOT / page).read_text()
    if page.endswith(".rst"):
        return [re.sub(r"^    ", "", body, flags=re.M) for kind, body in RST_BLOCK.findall(text) if kind == lang]
    return [body for kind, body in MD_BLOCK.findall(text) if kind == lang]


def skipped(line: str) -> bool:
    return "# yours" in line or "--device cuda" in line or re.match(r"^(pip install \S+ && )?pytest\b", line)


def commands(page: str) -> list[str]:
    lines = [ln.strip() for body in blocks(page, "bash") for ln in body.splitlines() if ln.strip()]
    return [re.sub(r"^pip install \S+ && ", "", ln) for ln in lines if not skipped(ln)]


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "WARPTAN_WARP_OUTPUT")}
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env.get("PATH", "")
    return env


def _workdir(tmp_path: Path) -> Path:
    (tmp_path / "campaigns").symlink_to(ROOT / "campaigns")
    return tmp_path


def test_the_pages_have_examples_and_mark_what_is_yours():
    """The extraction finds what the pages show (a change of fence would silently test nothing), and what it skips
    is what the pages mark."""
    assert len(blocks("docs/user-guide.md", "python")) >= 3 and len(blocks("docs/getting-started.rst", "python")) == 1
    assert [c.split("#")[0].strip() for c in commands("README.md")] == ["warptan run"]
    cmds = commands("docs/user-guide.md")
    assert any(c.startswith("warptan terrain info rugged") for c in cmds)
    assert any(c.startswith("warptan campaign campaigns/example_quick.toml") for c in cmds)
    assert not any("my_dem" in c or "flight.h5" in c or "HEAD:6379" in c for c in cmds)


@pytest.mark.slow
@pytest.mark.parametrize("page", ["docs/user-guide.md", "docs/getting-started.rst"])
def test_the_python_examples_run_as_written(tmp_path, page):
    code = "\n".join(ln for body in blocks(page, "python") for ln in body.splitlines() if "# yours" not in ln)
    proc = subprocess.run([sys.executable, "-c", code], cwd=_workdir(tmp_path), capture_output=True, text=True,
                          env=_env(), timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    printed = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    assert len(printed) == sum(body.count("print(") for body in blocks(page, "python")), proc.stdout  # results only


@pytest.mark.slow
@pytest.mark.parametrize("page", ["README.md", "docs/user-guide.md"])
def test_the_command_lines_run_as_written(tmp_path, page):
    work = _workdir(tmp_path)
    for line in commands(page):
        proc = subprocess.run(["bash", "-c", line], cwd=work, capture_output=True, text=True, env=_env(),
                              timeout=600)
        assert proc.returncode == 0, f"{line}\n{proc.stderr[-3000:]}"
        assert "Warp" not in proc.stdout and "Module" not in proc.stdout, proc.stdout  # (Warp's banner is off)


def test_every_picture_the_docs_show_is_in_the_repository():
    """The example plots (``docs/images``, made by ``scripts/docs_images.py``) and the results' figures the pages
    show exist where the pages point."""
    shown = 0
    for page in ["README.md", "docs/user-guide.md", "docs/results.md"]:
        for target in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", (ROOT / page).read_text()):
            assert (ROOT / page).parent.joinpath(target).resolve().is_file(), f"{page}: {target}"
            shown += 1
    assert shown >= 5 and all((ROOT / "docs" / "images" / n).is_file() for n in (
        "run_track.png", "run_errors.png", "information_S8.png", "campaign_particles.png"))


def test_the_project_cites_only_what_it_ships():
    """Self-contained (issue 67): no path outside the repository in README, docs, tests, scripts or the package, and
    the specification the code cites is the project's own design notes (``docs/design.md``, §1–§7 as cited), not a
    file a user never has."""
    design = (ROOT / "docs" / "design.md").read_text()
    sections = set(re.findall(r"^## (\d+b?)\. ", design, re.M))
    cited = set()
    outside = ("../" + "shared", "/work/" + "shared", "SPEC " + "§")
    for path in [ROOT / "README.md", *(ROOT / "docs").glob("*.*"), *(ROOT / "tests").glob("*.py"),
                 *(ROOT / "scripts").glob("*.py"), *(ROOT / "warptan").rglob("*.py"), *(ROOT / "kernels").rglob("*.py"),
                 *(ROOT / "warptan" / "scenario_files").glob("*.toml")]:
        if path.suffix not in (".md", ".rst", ".py", ".toml"):
            continue
        text = path.read_text()
        assert not any(word in text for word in outside), path
        cited |= set(re.findall(r"design notes (?:\([^)]*\) )?§(\d+b?)", text))
    assert cited and cited <= sections, cited - sections


def test_the_paths_the_docs_name_exist():
    """A module path the docs name (``warptan/nav/{ins,imu}.py`` included) is in the repository: docs/features.md
    listed paths that had moved."""
    missing = []
    for page in ["README.md", "docs/features.md", "docs/user-guide.md", "docs/design.md"]:
        for token in re.findall(r"`((?:warptan|kernels|scripts|campaigns)/[^`\s*]+\.(?:py|toml|md))`",
                                (ROOT / page).read_text()):
            brace = re.search(r"\{([^}]*)\}", token)
            names = [token[:brace.start()] + p + token[brace.end():] for p in brace.group(1).split(",")] \
                if brace else [token]
            missing += [f"{page}: {n}" for n in names if not (ROOT / n).exists()]
    assert not missing, missing


def test_the_synopses_name_every_option_of_the_commands():
    """The user guide's synopses hold every option ``--help`` shows (they missed ``--surface``, the information map's
    options, the bag topics, …)."""
    from warptan.cli import build_parser

    synopsis = re.search(r"```text\n(warptan run .*?)```", (ROOT / "docs/user-guide.md").read_text(), re.S).group(1)
    commands = build_parser()._subparsers._group_actions[0].choices
    parsers = [commands[c] for c in ("run", "replay", "campaign")]
    for group in ("terrain", "log"):
        parsers += list(commands[group]._subparsers._group_actions[0].choices.values())
    missing = {o for p in parsers for a in p._actions for o in a.option_strings
               if o.startswith("--") and o != "--help" and a.help != "==SUPPRESS=="
               and not re.search(re.escape(o) + r"(?![\w-])", synopsis)}  # (--map is not --map-error-m)
    assert not missing, sorted(missing)
