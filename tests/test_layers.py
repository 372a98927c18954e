"""The package's layers import only downward and no module imports itself back through others: common modules <
terrain < nav < sensing < filter < io < sim < cli (``warptan/__init__.py`` is the public façade over all of them;
``warptan.kernels`` are Warp kernels that import only each other). Every import counts, those inside functions too."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
COMMON = {"checks", "device", "parallel", "meta", "outputs", "progress"}
RANKS = {"kernels": 0, "common": 0, "terrain": 1, "nav": 2, "sensing": 3, "filter": 4, "io": 5, "sim": 6, "cli": 7}


def _modules() -> dict[str, Path]:
    """Every module of the package by dotted name (kernels/ is installed as warptan.kernels)."""
    out = {}
    for path in sorted((ROOT / "warptan").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    for path in sorted((ROOT / "kernels").rglob("*.py")):
        parts = ("warptan", "kernels", *path.relative_to(ROOT / "kernels").with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _layer(name: str) -> str | None:
    parts = name.split(".")
    if parts == ["warptan"]:
        return None  # the façade
    head = parts[1]
    if head in COMMON:
        return "common"
    if head in ("cli", "__main__"):
        return "cli"
    return head


def _imports(path: Path, modules: dict[str, Path]) -> list[tuple[int, str, str | None]]:
    """(line, imported module, imported name) for every warptan import of the file, resolved to a module."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name, None) for a in node.names if a.name.split(".")[0] == "warptan"]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "warptan":
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                found.append((node.lineno, sub, None) if sub in modules else (node.lineno, node.module, alias.name))
    return found


def test_every_module_is_in_a_layer():
    unknown = [name for name in _modules() if name != "warptan" and _layer(name) not in RANKS]
    assert not unknown, f"modules outside every layer: {unknown} (add them to a layer in tests/test_layers.py)"


def test_imports_go_only_downward():
    modules = _modules()
    upward = []
    for name, path in modules.items():
        layer = _layer(name)
        if layer is None:
            continue
        for line, target, what in _imports(path, modules):
            if target == "warptan":
                if what != "__version__":
                    upward.append(f"{path.relative_to(ROOT)}:{line} imports {what} from the package's façade")
                continue
            to = _layer(target)
            if (layer == "kernels" and to != "kernels") or RANKS.get(to, 99) > RANKS[layer]:
                upward.append(f"{path.relative_to(ROOT)}:{line} ({layer}) imports {target} ({to})")
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_no_import_cycle():
    modules = _modules()
    graph = {name: sorted({t for _, t, _ in _imports(path, modules) if t in modules and t != "warptan"})
             for name, path in modules.items() if name != "warptan"}
    state: dict[str, int] = {}
    cycles = []

    def visit(node, stack):
        state[node] = 1
        stack.append(node)
        for nxt in graph.get(node, []):
            if state.get(nxt) == 1:
                cycles.append([*stack[stack.index(nxt):], nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2

    for node in graph:
        if node not in state:
            visit(node, [])
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("bad", ["warptan.sim.runner", "warptan.cli"])
def test_the_check_sees_an_upward_import(tmp_path, monkeypatch, bad):
    """The checks above can fail: a terrain module importing the simulation or the CLI is flagged."""
    fake = tmp_path / "warptan" / "terrain"
    fake.mkdir(parents=True)
    (fake / "bad.py").write_text(f"def f():\n    import {bad}\n")
    modules = {"warptan.terrain.bad": fake / "bad.py", bad: Path("x")}
    line, target, _ = _imports(fake / "bad.py", modules)[0]
    assert (line, target) == (2, bad)
    assert RANKS[_layer(target)] > RANKS[_layer("warptan.terrain.bad")]
