"""The tree's shape, read from the source (ast): no cycles, no upward imports, a pure core, no import-time work.

The checks are functions of a tree (a folder per top-level package) so that they are also run on a
deliberately bad synthetic tree, which each of them must reject.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NAMESPACE = "stereopath"
FOLDERS = {"device": "stereopath.device", "host": "stereopath.host"}

# The layers, lowest first: a module may import its own layer or lower ones, never a higher one.
LAYERS: list[tuple[str, ...]] = [
    ("stereopath.device.errors", "stereopath.device.core"),
    # the simulator is pure synthesis; the typed configuration schema reads only core.config
    ("stereopath.device.sim", "stereopath.device.settings"),
    ("stereopath.device.wire", "stereopath.device.formats"),
    ("stereopath.device.estimation", "stereopath.device.capture"),
    ("stereopath.device.streaming",),
    ("stereopath.device.service",),
    ("stereopath.device.commands", "stereopath.device"),
    ("stereopath.host.progress",),
    ("stereopath.host.backend",),
    ("stereopath.host.evaluation", "stereopath.host.mapping", "stereopath.host.live", "stereopath.host.reprocess",
     "stereopath.host.fleet", "stereopath.host.export"),
    ("stereopath.host.commands", "stereopath.host"),
]
# What the pure core must not import: I/O libraries and our own I/O layers.
CORE = "stereopath.device.core"
CORE_FORBIDDEN = ("zmq", "smbus2", "picamera2", "depthai", "open3d", "socket", "stereopath.device.formats",
                  "stereopath.device.wire", "stereopath.device.streaming", "stereopath.device.service",
                  "stereopath.device.capture")


@dataclass
class Module:
    name: str
    path: Path
    is_package: bool
    imports: set[str] = field(default_factory=set)        # every import, wherever it stands
    top_calls: list[str] = field(default_factory=list)    # module-level call statements (import-time work)


def _resolve(mod: Module, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = mod.name.split(".")
    base = base if mod.is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def scan(folders: dict[str, str], root: Path) -> dict[str, Module]:
    """Every module under ``root/<folder>`` named by the installed package of its folder."""
    modules: dict[str, Module] = {}
    for folder, package in folders.items():
        for path in sorted((root / folder).rglob("*.py")):
            rel = path.relative_to(root / folder).with_suffix("")
            parts = list(rel.parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            name = ".".join([package, *parts])
            modules[name] = Module(name, path, is_package)
    for mod in modules.values():
        tree = ast.parse(mod.path.read_text(), str(mod.path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mod.imports.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(mod, node)
                mod.imports.add(base)
                mod.imports.update(f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in modules)
        for node in tree.body if mod.path.name != "__main__.py" else ():  # running is __main__'s job
            if isinstance(node, ast.Expr) and isinstance(node.value, ast.Call):
                mod.top_calls.append(f"{mod.path.name}:{node.lineno} {ast.unparse(node.value)[:60]}")
    return modules


def _own(name: str, modules: dict[str, Module]) -> str | None:
    """The module of ours that ``import name`` loads (the longest known prefix)."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        candidate = ".".join(parts[:n])
        if candidate in modules:
            return candidate
    return None


def graph(modules: dict[str, Module]) -> dict[str, set[str]]:
    g: dict[str, set[str]] = {}
    for mod in modules.values():
        deps = {_own(i, modules) for i in mod.imports}
        g[mod.name] = {d for d in deps if d is not None and d != mod.name}
    # importing a.b.c runs a/__init__ and a/b/__init__ too, but those are parents: not counted as edges
    return g


def cycles(modules: dict[str, Module]) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan), ignoring edges to a module's own packages."""
    g = graph(modules)
    for name in g:
        g[name] = {d for d in g[name] if not name.startswith(d + ".")}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def layer_of(name: str, layers: list[tuple[str, ...]]) -> int | None:
    best: tuple[int, int] | None = None  # (prefix length, layer)
    for rank, prefixes in enumerate(layers):
        for p in prefixes:
            if name == p or name.startswith(p + "."):
                if best is None or len(p) > best[0]:
                    best = (len(p), rank)
    return None if best is None else best[1]


def upward_imports(modules: dict[str, Module], layers: list[tuple[str, ...]]) -> list[str]:
    bad = []
    for name, deps in graph(modules).items():
        me = layer_of(name, layers)
        for d in sorted(deps):
            if name.startswith(d + "."):
                continue  # a package's own __init__
            them = layer_of(d, layers)
            if me is not None and them is not None and them > me:
                bad.append(f"{name} -> {d}")
    return bad


def side_imports(modules: dict[str, Module], importer: str, forbidden: tuple[str, ...]) -> list[str]:
    bad = []
    for mod in modules.values():
        if mod.name == importer or mod.name.startswith(importer + "."):
            for i in sorted(mod.imports):
                if any(i == f or i.startswith(f + ".") for f in forbidden):
                    bad.append(f"{mod.name} -> {i}")
    return bad


def import_time_calls(modules: dict[str, Module]) -> list[str]:
    return [c for mod in modules.values() for c in mod.top_calls]


def missing_packages(modules: dict[str, Module], pyproject: str) -> list[str]:
    block = re.search(r"^packages\s*=\s*\[(.*?)\]", pyproject, re.S | re.M)
    listed = set(re.findall(r'"([^"]+)"', block.group(1))) if block else set()
    return sorted(m.name for m in modules.values() if m.is_package and m.name not in listed)


# ---------------------------------------------------------------------------------------- the tree


@pytest.fixture(scope="module")
def tree() -> dict[str, Module]:
    return scan(FOLDERS, ROOT)


def test_no_import_cycle(tree):
    assert cycles(tree) == []


def test_device_never_imports_host(tree):
    assert side_imports(tree, "stereopath.device", ("stereopath.host",)) == []


def test_core_imports_nothing_with_io(tree):
    assert side_imports(tree, CORE, CORE_FORBIDDEN) == []


def test_no_upward_import(tree):
    assert upward_imports(tree, LAYERS) == []


def test_every_package_folder_is_installed(tree):
    assert missing_packages(tree, (ROOT / "pyproject.toml").read_text()) == []


def test_every_module_has_a_layer(tree):
    assert [m for m in sorted(tree) if layer_of(m, LAYERS) is None] == []


def test_nothing_runs_at_import(tree):
    assert import_time_calls(tree) == []


# ---------------------------------------------------------------------------------------- a bad tree


BAD_TREE = {
    "device/__init__.py": "",
    "device/core/__init__.py": "",
    "device/core/geometry.py": "import zmq\nfrom stereopath.device.formats import tum\n",
    "device/formats/__init__.py": "",
    "device/formats/tum.py": "from ..core import geometry\nfrom stereopath.device.service import run\n",
    "device/service/__init__.py": "",
    "device/service/run.py": "from stereopath.host import view\n",
    "device/sim/source.py": "def _register():\n    pass\n\n\n_register()\n",
    "host/__init__.py": "",
    "host/view.py": "",
}


def test_each_check_rejects_a_bad_tree(tmp_path):
    for rel, text in BAD_TREE.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    bad = scan(FOLDERS, tmp_path)
    assert cycles(bad) == [["stereopath.device.core.geometry", "stereopath.device.formats.tum"]]
    assert side_imports(bad, "stereopath.device", ("stereopath.host",)) == \
        ["stereopath.device.service.run -> stereopath.host", "stereopath.device.service.run -> stereopath.host.view"]
    assert side_imports(bad, CORE, CORE_FORBIDDEN) == \
        ["stereopath.device.core.geometry -> stereopath.device.formats",
         "stereopath.device.core.geometry -> stereopath.device.formats.tum",
         "stereopath.device.core.geometry -> zmq"]
    assert upward_imports(bad, LAYERS) == [
        "stereopath.device.core.geometry -> stereopath.device.formats",
        "stereopath.device.core.geometry -> stereopath.device.formats.tum",
        "stereopath.device.formats.tum -> stereopath.device.service",
        "stereopath.device.formats.tum -> stereopath.device.service.run",
        "stereopath.device.service.run -> stereopath.host",
        "stereopath.device.service.run -> stereopath.host.view"]
    assert missing_packages(bad, 'packages = [\n    "stereopath.device",\n    "stereopath.host",\n]\n') == \
        ["stereopath.device.core", "stereopath.device.formats", "stereopath.device.service"]
    assert import_time_calls(bad) == ["source.py:5 _register()"]
