"""Packaging: the installed layout (warptan + warptan.kernels) and the command line."""

import os
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_import_needs_only_numpy_and_warp():
    """`import warptan` pulls in neither rasterio, trimesh nor matplotlib (the bare-GPU-machine case), nor Ray (the
    campaign engine imports it only when it runs)."""
    code = ("import sys, warptan, warptan.kernels.terrain, warptan.sim.campaign; "
            "bad = [m for m in ('rasterio', 'trimesh', 'matplotlib', 'tqdm', 'ray') if m in sys.modules]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, cwd="/")


def test_help_and_the_public_names_load_nothing_until_used():
    """`import warptan` and the command's parser load neither Warp nor NumPy (`warptan --help` and usage errors come
    at once: scripts/bench_cli_start.py); every public name of `warptan.__all__` loads on first use, and a name that
    is not one is an AttributeError."""
    code = ("import sys, warptan, warptan.cli; warptan.cli.build_parser().format_help(); "
            "assert 'warp' not in sys.modules and 'numpy' not in sys.modules, sorted(sys.modules); "
            "assert set(warptan.__all__) <= set(dir(warptan)); "
            "[getattr(warptan, name) for name in warptan.__all__]; "
            "assert warptan.frames.__name__ == 'warptan.nav.frames' and 'warp' in sys.modules; "
            "assert not hasattr(warptan, 'no_such_name')")
    subprocess.run([sys.executable, "-c", code], check=True, cwd="/")
    proc = subprocess.run([sys.executable, "-m", "warptan", "--help"], capture_output=True, text=True, cwd="/")
    assert proc.returncode == 0 and "--device" not in proc.stdout and "run" in proc.stdout and not proc.stderr


def test_the_api_prints_nothing_of_warps_unless_asked():
    """A scenario run through the API writes nothing on stdout (Warp's banner and "Module … load" lines are off);
    ``WARPTAN_WARP_OUTPUT=1`` keeps them."""
    code = ("import warptan; warptan.run_scenario('S8', duration_s=0.2, particles=16, bound=False, device='cpu'); "
            "import warp; print('quiet' if getattr(warp.config, 'quiet', False) else 'verbose')")
    env = {k: v for k, v in os.environ.items() if k != "WARPTAN_WARP_OUTPUT"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/", env=env)
    assert proc.returncode == 0 and proc.stdout == "quiet\n", proc.stdout + proc.stderr
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/",
                          env={**env, "WARPTAN_WARP_OUTPUT": "1"})
    assert proc.returncode == 0 and proc.stdout.endswith("verbose\n") and "Warp" in proc.stdout, proc.stdout


@pytest.mark.slow
def test_fresh_virtualenv_install(tmp_path):
    """`pip install .` into a fresh venv gives warptan and warptan.kernels; `import kernels` is not ours. Works
    from inside a virtualenv too (the README's own install): the child environment sees the running
    interpreter's site-packages through a .pth file (its dependencies and setuptools), not the system's."""
    env_dir = tmp_path / "venv"
    # No pip of its own: ensurepip would also put its bundled setuptools (65 on Python 3.11, no bdist_wheel) in front
    # of the parent's; pip, setuptools and the dependencies all come from the parent through the .pth below.
    venv.EnvBuilder(system_site_packages=False, with_pip=False).create(env_dir)
    py = str(env_dir / "bin" / "python")
    child_site = subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], check=True,
                                capture_output=True, text=True).stdout.strip()
    parent = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    Path(child_site, "_parent_env.pth").write_text("\n".join(sorted(parent)) + "\n")
    # --no-deps/--no-build-isolation: the dependencies and setuptools come from the parent environment: no network.
    subprocess.run([py, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", str(ROOT)],
                   check=True, cwd=tmp_path)
    code = ("import importlib.util, warptan, warptan.kernels, warptan.kernels.terrain; "
            "import os; "
            f"assert os.path.realpath(warptan.kernels.__file__).startswith({os.path.realpath(env_dir)!r}), "
            "warptan.kernels.__file__; "
            "spec = importlib.util.find_spec('kernels'); "
            "assert spec is None or 'warptan' not in (spec.origin or ''), spec; "
            # the scenarios' real terrains come with the package (issue 13): no file outside it, no environment variable
            "from warptan.sim.scenarios import prepare; cfg, truth, flight = prepare('S8'); "
            "assert truth.name == 'rugged:thuringia_hilly_srtm3_crop44km.tif', truth.name; "
            "assert 'site-packages' in truth.description, truth.description; print(warptan.kernels.__file__)")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "WARPTAN_DEM_DIR")}
    out = subprocess.run([py, "-c", code], check=True, cwd=tmp_path, capture_output=True, text=True, env=env)
    assert "warptan/kernels/__init__.py" in out.stdout
    version = subprocess.run([py, "-m", "warptan", "--version"], check=True, cwd=tmp_path, capture_output=True,
                             text=True, env=env)
    import warptan

    assert version.stdout.strip() == f"warptan {warptan.__version__}"
    # the installed copy names the commit it was built from (results.json's git_commit; it said "unknown" before)
    built = subprocess.run([py, "-c", "from warptan.meta import git_commit; print(git_commit())"], check=True,
                           cwd=tmp_path, capture_output=True, text=True, env=env).stdout.strip()
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    assert built.startswith(head) and built.endswith(" (installed)"), built


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "warptan.cli", *args], capture_output=True, text=True, cwd="/")


def test_cli_terrain_info_default_and_export(tmp_path):
    """`warptan terrain info` describes the generated default terrain; export writes a PLY."""
    out = _cli("terrain", "info")
    assert out.returncode == 0, out.stderr
    assert "synthetic:rugged" in out.stdout and "nodata" in out.stdout and "spacing" in out.stdout
    ply = tmp_path / "t.ply"
    out = _cli("terrain", "export", "synthetic:flat,size_m=2000,spacing=50", str(ply))
    assert out.returncode == 0, out.stderr
    assert ply.stat().st_size > 1000


@pytest.mark.parametrize(("spec", "message"), [
    ("/no/such/file.dt1", "DEM file not found: /no/such/file.dt1"),
    ("synthetic:bumpy", "unknown synthetic terrain kind 'bumpy'"),
    ("synthetic:rugged,spacing=-1", "spacing must be a positive number"),
    ("synthetic:rugged,colour=red", "bad option"),
])
def test_cli_bad_terrain_is_a_clear_error(spec, message):
    """Bad terrain arguments exit 2 with one line naming the problem, no traceback."""
    out = _cli("terrain", "info", spec)
    assert out.returncode == 2
    assert message in out.stderr and "Traceback" not in out.stderr


def test_the_help_tells_simulated_damage_from_what_the_filter_is_told():
    """`warptan run --help`: the options that simulate a wrong map or world say so and that the filter is not told;
    `--map-error-m` says it tells the filter and simulates nothing (their help texts were the same words)."""
    from warptan.cli import build_parser

    parser = build_parser()
    sub = parser._subparsers._group_actions[0].choices["run"]
    helps = {a.option_strings[0]: a.help for a in sub._actions if a.option_strings}
    for option in ("--sim-map-noise-m", "--sim-map-bias-m", "--sim-map-spacing-m", "--world-error-m"):
        assert helps[option].startswith("SIMULATES") and "not told" in helps[option], option
    assert helps["--map-error-m"].startswith("TELLS the filter") and "simulates nothing" in helps["--map-error-m"]


def test_the_old_names_of_the_simulated_damage_still_work_with_a_warning(capsys):
    """--map-noise-m, --map-bias-m and --map-spacing-m (renamed --sim-map-*: they simulate, --map-error-m tells)
    stay one release as hidden aliases: the same value, and a warning naming the new option."""
    from warptan.cli import build_parser

    parser = build_parser()
    for old, new, value in (("--map-noise-m", "--sim-map-noise-m", "1.5"), ("--map-bias-m", "--sim-map-bias-m", "-2"),
                            ("--map-spacing-m", "--sim-map-spacing-m", "180")):
        a = parser.parse_args(["run", "S8", old, value])
        warned = capsys.readouterr().err
        b = parser.parse_args(["run", "S8", new, value])
        assert vars(a) == vars(b) and f"{old} is deprecated" in warned and new in warned
        assert capsys.readouterr().err == ""
    assert "--map-noise-m" not in parser._subparsers._group_actions[0].choices["run"].format_help()
