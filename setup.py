"""The build records the commit it was built from (``warptan/BUILD_COMMIT`` in the wheel), so that an installed,
non-editable copy of a clone still names its commit in every ``results.json`` (:func:`warptan.meta.git_commit`).
Everything else about the package is in pyproject.toml."""

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent


def source_commit() -> str | None:
    """The clone's commit as :func:`warptan.meta.git_commit` names it (``+dirty`` when tracked files differ), None
    outside a git checkout or without git. ``warptan/meta.py`` is loaded by its path: the build has neither the
    package installed nor its dependencies (the module's own imports are the standard library's)."""
    spec = importlib.util.spec_from_file_location("_warptan_meta", HERE / "warptan" / "meta.py")
    meta = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(meta)
    commit = meta.git_commit(HERE)
    return None if commit.startswith("unknown") else commit


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
