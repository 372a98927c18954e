"""The build records the commit it was built from (``warptan/BUILD_COMMIT`` in the wheel), so that an installed,
non-editable copy of a clone still names its commit in every ``results.json`` (:func:`warptan.meta.git_commit`).
Everything else about the package is in pyproject.toml."""

import subprocess
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent


def source_commit() -> str | None:
    """The clone's commit (``+dirty`` when tracked files differ), None outside a git checkout or without git."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=HERE, capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "--no-optional-locks", "status", "--porcelain", "--untracked-files=no"],
                               cwd=HERE, capture_output=True, text=True, timeout=10).stdout.strip()
        return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


class BuildWithCommit(build_py):
    def run(self):
        super().run()
        commit = source_commit()
        target = Path(self.build_lib, "warptan", "BUILD_COMMIT")
        target.unlink(missing_ok=True)  # (a reused build folder keeps an earlier build's file)
        if commit and not self.editable_mode:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(commit + "\n")


setup(cmdclass={"build_py": BuildWithCommit})
