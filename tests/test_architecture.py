"""The package graph stays as docs/architecture.md draws it: no import cycles, and light
modules stay light."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("palette_core", "harmonize", "nerf_stage", "studio")


def _modules() -> dict[str, Path]:
    modules = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules that ``name`` imports, anywhere in its file (function bodies too),
    and, in a module that imports by name (``importlib``), the modules its strings name
    (``"splats.backbone"``, ``"fields.grid:GridField"``; dict keys are names, not modules)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    tree = ast.parse(path.read_text())
    if any(isinstance(node, ast.Import) and any(a.name == "importlib" for a in node.names)
           for node in ast.walk(tree)):
        keys = {id(key) for node in ast.walk(tree) if isinstance(node, ast.Dict)
                for key in node.keys}
        top = name.split(".")[0]
        found |= {f"{top}.{node.value.split(':')[0]}" for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str)
                  and id(node) not in keys}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name in modules}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([node.module] if node.module else []))
            for alias in node.names:
                target = f"{base}.{alias.name}"
                found.add(target if target in modules else base)
    return found & modules.keys()


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in graph[node]:
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return cycles


def test_no_import_cycle_in_the_package_graph():
    modules = _modules()
    graph = {name: _imports(name, path, modules) - {name} for name, path in modules.items()}
    assert _cycles(graph) == []


def test_imports_by_name_are_imports():
    modules = _modules()
    found = _imports("nerf_stage.backbones", modules["nerf_stage.backbones"], modules)
    assert {"nerf_stage.splats.backbone", "nerf_stage.fields.grid"} <= found
    assert "nerf_stage.splats" not in found  # the table's key "splats", a name


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("module, heavy", [("nerf_stage.train.metrics", ("numba", "torch")),
                                           ("nerf_stage.backbones", ("torch",)),
                                           ("nerf_stage.data.dataset", ("torch", "pycolmap")),
                                           ("palette_core", ("torch", "zarr", "viser"))])
def test_light_modules_import_no_heavy_dependency(module, heavy):
    code = f"import sys, {module}; print(*[m for m in {heavy!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    assert out.stdout.strip() == ""


#: Kernel modules, whose numba functions take flat arrays and so run long, may pass 400 lines.
KERNELS = {"nerf_stage.simulation.pathtracer"}


def test_modules_and_functions_stay_short():
    long_modules, long_functions = [], []
    for name, path in _modules().items():
        tree = ast.parse(path.read_text())
        if name not in KERNELS and tree.body and tree.body[-1].end_lineno > 400:
            long_modules.append(name)
        long_functions += [f"{name}.{node.name}" for node in ast.walk(tree)
                           if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                           and node.end_lineno - node.lineno >= 80]
    assert not long_modules and not long_functions
