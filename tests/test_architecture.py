"""The layering rules of docs/architecture.md, checked on the source: what may import what, and file sizes.

Imports are read with ``ast`` from every module under ``nvs/``, at any depth (a function-level import counts: it
hides a dependency, it does not remove it).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "nvs"
MAX_LINES = 300


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


SOURCES = _sources()


def _is_cli(name: str, path: Path) -> bool:
    """An entry point: a ``__main__`` module, or one that runs itself under ``if __name__ == "__main__"``."""
    return name.endswith(".__main__") or 'if __name__ == "__main__"' in path.read_text()


CLIS = {name for name, path in SOURCES.items() if _is_cli(name, path)}


def _resolve(name: str, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = name.split(".")
    if not SOURCES[name].name == "__init__.py":
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(name: str) -> set[str]:
    """Every module ``name`` imports (absolute names; ``from a import b`` yields ``a.b`` when that is a module)."""
    tree = ast.parse(SOURCES[name].read_text(), filename=str(SOURCES[name]))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            mod = _resolve(name, node)
            out.add(mod)
            out.update(f"{mod}.{alias.name}" for alias in node.names if f"{mod}.{alias.name}" in SOURCES)
    return out


def _nvs_imports(name: str) -> set[str]:
    """The nvs modules ``name`` imports, each reduced to a module that exists (``nvs.x.y`` -> ``nvs.x``)."""
    found = set()
    for mod in imports_of(name):
        while mod and mod not in SOURCES:
            mod = mod.rpartition(".")[0]
        if mod.startswith("nvs") and mod != "nvs" and mod != name:
            found.add(mod)
    return found


GRAPH = {name: _nvs_imports(name) for name in SOURCES}


def _under(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def test_the_cli_list_is_what_the_docs_name():
    # A guard for the detection itself: these are entry points users type, so they must be found as CLIs.
    for cli in ("nvs.train", "nvs.evaluate", "nvs.convert", "nvs.demo"):
        assert cli in CLIS, f"{cli} is not detected as a CLI"


def test_no_module_imports_a_cli():
    bad = sorted(f"{name} imports {dep}" for name, deps in GRAPH.items() for dep in deps
                 if dep in CLIS and not (name.endswith(".__main__") and dep == name.rsplit(".", 1)[0]))
    assert not bad, "a CLI is imported by another module:\n" + "\n".join(bad)


def test_no_import_circle():
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for dep in sorted(GRAPH[node]):
            if state.get(dep) == 1:
                return stack[stack.index(dep):] + [dep]
            if dep not in state and (found := visit(dep)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for name in sorted(GRAPH):
        if name not in state and (circle := visit(name)):
            pytest.fail("import circle: " + " -> ".join(circle))


@pytest.mark.parametrize("layer", ["nvs.geometry", "nvs.types", "nvs.models", "nvs.perceptual"])
def test_core_layers_import_no_data_lightning_or_tool(layer):
    names = [n for n in SOURCES if _under(n, (layer,))]
    assert names, f"{layer} does not exist"
    forbidden_nvs = ("nvs.data", "nvs.module", "nvs.build", "nvs.losses", "nvs.metrics", "nvs.sweep", "nvs.stress",
                     "nvs.bench", "nvs.viewer", "nvs.checkpoints")
    bad = []
    for name in names:
        for mod in imports_of(name):
            if _under(mod, ("lightning", "pytorch_lightning", "hydra", "pandas")) or _under(mod, forbidden_nvs) \
                    or mod in CLIS:
                bad.append(f"{name} imports {mod}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("judge", ["nvs.losses", "nvs.losses_branches", "nvs.losses_adversarial", "nvs.metrics"])
def test_losses_and_metrics_import_no_model_code(judge):
    bad = sorted(dep for dep in GRAPH[judge] if _under(dep, ("nvs.models",)))
    assert not bad, f"{judge} imports model code: {bad}"


def test_no_file_over_the_size_limit():
    long = {str(p.relative_to(PKG.parent)): n for p in PKG.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"files over {MAX_LINES} lines: {long}"


def test_the_sweep_recorder_loads_no_heavy_library():
    # Every training job of a sweep loads the recorder as a Hydra callback: it must cost no import time.
    code = ("import sys, nvs.sweep.recorder; heavy = [m for m in ('lightning', 'pandas', 'nvs.build', 'nvs.module', "
            "'nvs.data') if m in sys.modules]; print(heavy); sys.exit(1 if heavy else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def test_provenance_loads_no_lightning():
    code = "import sys, nvs.provenance; sys.exit(1 if 'lightning' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_the_detector_sees_a_known_edge():
    # nvs.build wires the module: if this edge vanished the import reader is broken, not the code clean.
    assert "nvs.module" in GRAPH["nvs.build"]
