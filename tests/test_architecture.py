"""The layering rules of docs/architecture.md, checked on the source: what may import what, and file sizes.

Imports are read with ``ast`` from every module under ``nvs/``, at any depth (a function-level import counts: it
hides a dependency, it does not remove it).
"""

from __future__ import annotations

import ast
import re
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


# The layers, bottom up (docs/architecture.md): a folder of nvs/ may import its own folder and the layers below it,
# never a sibling of its own layer or anything above. The CLIs (nvs/<x>.py, the packages' __main__) sit on top.
LAYERS = (
    ("nvs.core",),
    ("nvs.data", "nvs.models"),
    ("nvs.losses", "nvs.metrics"),
    ("nvs.module",),
    ("nvs.run",),
    ("nvs.report",),
    ("nvs.sweep", "nvs.stress", "nvs.bench", "nvs.viewer"),
)
FOLDERS = {folder: level for level, folders in enumerate(LAYERS) for folder in folders}


def folder_of(name: str) -> str | None:
    """The layer folder a module belongs to (``nvs.run.training`` -> ``nvs.run``); None for the package root."""
    parts = name.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 and ".".join(parts[:2]) in FOLDERS else None


def test_every_folder_is_a_layer_and_the_root_holds_only_clis():
    folders = {p.name for p in PKG.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert {f"nvs.{f}" for f in folders} == set(FOLDERS), "a folder of nvs/ that is not in LAYERS, or the reverse"
    loose = sorted(n for n, p in SOURCES.items() if p.parent == PKG and n != "nvs" and n not in CLIS)
    assert not loose, f"library modules at the package root (they belong in a layer folder): {loose}"


def layer_breaks(name: str, deps: set[str]) -> list[str]:
    """The imports of module ``name`` that point to a sibling of its layer, a layer above or the package root."""
    own, bad = folder_of(name), []
    for dep in sorted(deps):
        target = folder_of(dep)
        if target is None:
            bad.append(f"{dep} (the package root: a CLI)")
        elif target != own and FOLDERS[target] >= FOLDERS[own]:
            bad.append(f"{dep} ({'a sibling of its layer' if FOLDERS[target] == FOLDERS[own] else 'a layer above'})")
    return bad


@pytest.mark.parametrize("name", sorted(n for n in SOURCES if folder_of(n) and n not in CLIS))
def test_a_module_imports_only_its_folder_and_the_layers_below(name):
    bad = layer_breaks(name, GRAPH[name])
    assert not bad, f"{name} imports " + ", ".join(bad)


def test_the_layer_check_sees_a_known_edge_and_reports_made_up_breaks():
    # guards for the checker itself: the run layer builds the module (an edge the reader must see), and an import
    # upwards, sideways or of a CLI is reported while one downwards is not
    assert "nvs.module.lightning_module" in GRAPH["nvs.run.build"]
    assert layer_breaks("nvs.module.lightning_module", {"nvs.sweep.jobs"}) == ["nvs.sweep.jobs (a layer above)"]
    assert layer_breaks("nvs.data.kitti", {"nvs.models.net"}) == ["nvs.models.net (a sibling of its layer)"]
    assert layer_breaks("nvs.run.training", {"nvs.train"}) == ["nvs.train (the package root: a CLI)"]
    assert layer_breaks("nvs.run.training", {"nvs.core.errors", "nvs.run.build", "nvs.module.gather"}) == []


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


@pytest.mark.parametrize("layer", ["nvs.core.geometry", "nvs.core.types", "nvs.models", "nvs.models.perceptual"])
def test_core_layers_import_no_data_lightning_or_tool(layer):
    names = [n for n in SOURCES if _under(n, (layer,))]
    assert names, f"{layer} does not exist"
    forbidden_nvs = ("nvs.data", "nvs.module", "nvs.run", "nvs.losses", "nvs.metrics", "nvs.report", "nvs.sweep",
                     "nvs.stress", "nvs.bench", "nvs.viewer")
    bad = []
    for name in names:
        for mod in imports_of(name):
            if _under(mod, ("lightning", "pytorch_lightning", "hydra", "pandas")) or _under(mod, forbidden_nvs) \
                    or mod in CLIS:
                bad.append(f"{name} imports {mod}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("judge", sorted(n for n in SOURCES if _under(n, ("nvs.losses", "nvs.metrics"))))
def test_losses_and_metrics_import_no_model_code(judge):
    # the frozen VGG16 / LPIPS judges (models/perceptual.py) are what losses and metrics are made of; no network is
    bad = sorted(dep for dep in GRAPH[judge] if _under(dep, ("nvs.models",)) and dep != "nvs.models.perceptual")
    assert not bad, f"{judge} imports model code: {bad}"


def test_no_file_over_the_size_limit():
    long = {str(p.relative_to(PKG.parent)): n for p in PKG.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"files over {MAX_LINES} lines: {long}"


def test_the_sweep_recorder_loads_no_heavy_library():
    # Every training job of a sweep loads the recorder as a Hydra callback: it must cost no import time.
    code = ("import sys, nvs.sweep.recorder; heavy = [m for m in ('lightning', 'pandas', 'nvs.run.build', "
            "'nvs.module.lightning_module', 'nvs.data') if m in sys.modules]; print(heavy); sys.exit(1 if heavy else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def test_provenance_loads_no_lightning():
    code = "import sys, nvs.core.provenance; sys.exit(1 if 'lightning' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_the_tree_in_docs_architecture_is_the_tree():
    # docs/architecture.md draws the layers as a tree: each folder with its layer number, the modules of the
    # library folders by name, the CLIs at the root. A module added, moved or removed without the map fails here.
    text = (PKG.parent / "docs" / "architecture.md").read_text()
    block = text.split("```", 2)[1]
    words = set(re.findall(r"[\w.]+", block))
    drawn: dict[str, int] = {}
    lines = block.splitlines()
    for i, line in enumerate(lines):
        head = re.match(r"^  ((?:\w+/ ?)+)\s*(\d)?\s", line + " ")
        if not head:
            continue
        level = head.group(2) or re.match(r"^\s+(\d)\s", lines[i + 1]).group(1)
        for folder in re.findall(r"(\w+)/", head.group(1)):
            drawn[f"nvs.{folder}"] = int(level)
    assert drawn == FOLDERS, f"folders and layers drawn {drawn} != {FOLDERS}"
    named = ("nvs.core", "nvs.losses", "nvs.metrics", "nvs.module", "nvs.run", "nvs.report")
    missing = sorted(n for n in SOURCES if _under(n, named) and n not in named and n.rsplit(".", 1)[1] not in words)
    assert not missing, f"modules not named in docs/architecture.md's tree: {missing}"
    root_clis = sorted(p.name for p in PKG.glob("*.py") if p.name != "__init__.py")
    assert [c for c in root_clis if c not in words] == [], "a CLI at the root is not drawn"
