"""The package's layers import only downward and no module imports itself back through others: common modules <
terrain < nav < sensing < filter < io < sim < cli (``warptan/__init__.py`` is the public façade over all of them;
``warptan.kernels`` are Warp kernels that import only each other). Every import counts, those inside functions too."""

import ast
from pathlib import Path

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


def _upward(modules: dict[str, Path]) -> list[str]:
    """Every import of ``modules`` that goes to a higher layer (or, from a kernel, out of the kernels)."""
    found = []
    for name, path in modules.items():
        layer = _layer(name)
        if layer is None:
            continue
        for line, target, what in _imports(path, modules):
            where = f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}:{line}"
            if target == "warptan":
                if what != "__version__":
                    found.append(f"{where} imports {what} from the package's façade")
                continue
            to = _layer(target)
            if (layer == "kernels" and to != "kernels") or RANKS.get(to, 99) > RANKS[layer]:
                found.append(f"{where} ({layer}) imports {target} ({to})")
    return found


def _cycles(modules: dict[str, Path]) -> list[list[str]]:
    """The import cycles among ``modules`` (each as the path that closes it)."""
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
    return cycles


def test_imports_go_only_downward():
    upward = _upward(_modules())
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_no_import_cycle():
    cycles = _cycles(_modules())
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_the_checks_see_an_upward_import_and_a_cycle(tmp_path):
    """The checks above can fail: a terrain module importing the simulation inside a function is upward, and two
    simulation modules importing each other are a cycle."""
    root = tmp_path / "warptan"
    (root / "terrain").mkdir(parents=True)
    (root / "sim").mkdir()
    files = {"warptan.terrain.bad": "def f():\n    from warptan.sim.a import x\n",
             "warptan.sim.a": "from warptan.sim.b import y\nx = 1\n",
             "warptan.sim.b": "import warptan.sim.a\ny = 2\n"}
    modules = {}
    for name, text in files.items():
        path = tmp_path.joinpath(*name.split(".")).with_suffix(".py")
        path.write_text(text)
        modules[name] = path
    upward = _upward(modules)
    assert len(upward) == 1 and "(terrain) imports warptan.sim.a (sim)" in upward[0]
    cycles = _cycles(modules)
    assert cycles and set(cycles[0]) == {"warptan.sim.a", "warptan.sim.b"}


MAX_LINES = 520
"""About 500 lines: a module above this says at its top why it is one module."""


def test_big_modules_say_why():
    """No module is over ~500 lines unless a comment at its top (before its docstring) says why."""
    unexplained = []
    for name, path in _modules().items():
        text = path.read_text()
        if text.count("\n") > MAX_LINES and not text.startswith("# "):
            unexplained.append(f"{name} ({text.count(chr(10))} lines)")
    assert not unexplained, f"modules over {MAX_LINES} lines with no comment at their top saying why: {unexplained}"
