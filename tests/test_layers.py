"""The import structure of ``garmentnerf``: layers that only import downwards, and no import cycles.

Every module under ``garmentnerf/`` is parsed with :mod:`ast`. Every import statement counts, at
any depth (inside functions, under ``TYPE_CHECKING``, in ``try`` blocks); relative imports are
resolved against the importing module's package. An import names the deepest module it reaches:
``from garmentnerf.a.b import c`` is the module ``garmentnerf.a.b.c`` when there is one, else
``garmentnerf.a.b``.

A module belongs to a *unit*: the top-level package or module of ``garmentnerf`` it lives in
(``garmentnerf/model/pipeline.py`` is in ``model``, ``garmentnerf/runs.py`` is ``runs``). Units sit
in the ordered layers of :data:`LAYERS`. A module may import its own unit and the units of lower
layers; an import of a higher layer fails the test, and so does an import between two units of
one layer unless :data:`SAME_LAYER_IMPORTS` allows it. Independently of the layers, no two modules
may import each other, directly or round a longer circle.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

PACKAGE = "garmentnerf"
PACKAGE_ROOT = Path(__file__).resolve().parent.parent
#: The unit of the package's own ``__init__.py``.
ROOT_UNIT = "__init__"

#: The units of ``garmentnerf``, lowest layer first.
LAYERS: tuple[tuple[str, ...], ...] = (
    # The ground: camera and array conventions, safe file writes, signals, closeable objects, the
    # machine's CPU load, the package version, the byte-bounded cache, frame ranges and lists, argument
    # budgets, the folder lock, the checks of a command's output before it is written, the package's data
    # files (body asset, demos, shaders) and the package's own (empty) __init__. They import nothing of
    # garmentnerf.
    ("conventions", "io_utils", "interrupts", "lifecycle", "cpu_load", "version", "byte_lru", "ranges", "budgets",
     "folder_lock", "output_checks", "assets", "shaders", ROOT_UNIT),
    # Reading pickled files without running their code (reads .npy headers with io_utils); the
    # command's start time and the machine's load since then (reads cpu_load).
    ("safe_pickle", "startup"),
    # The body model: template, shape, skinning, UV atlas, shading basis.
    ("body",),
    # Body motions; the geometry of points against the body surface. Independent of each other.
    ("motion", "geometry"),
    # The networks: plain torch on tensors. No GL (GL results come in as tensors), no scene files.
    ("model",),
    # The OpenGL passes (moderngl), each owning its GL objects.
    ("gl",),
    # Scenes, their ground-truth images (GL), simulated garments, datasets.
    ("data",),
    # The run folder: run.json, the model's weights, loading a run.
    ("runs",),
    # Rendering a run: the one render path of every tool; the GL passes that feed the model.
    ("render",),
    # Baked frames: the garment rendered once from a ring of cameras, kept, and drawn from any camera by GL.
    ("bake",),
    # The bundled demos: run folders shipped in the package (packing one measures its garment's band).
    ("demos",),
    # Training (renders with the render presets).
    ("train",),
    # Evaluation (renders runs, reads the trainer's frames, checkpoints and settings).
    ("eval",),
    # The desktop previewer and the benchmarks: two independent users of everything below.
    ("viewer", "perf"),
    # The command line: the one entry point.
    ("cli",),
)

#: (importing unit, imported unit) pairs of one layer that may import each other's modules: none.
SAME_LAYER_IMPORTS: frozenset[tuple[str, str]] = frozenset()


@dataclass(frozen=True)
class Import:
    """One import of a package module by another: ``source`` imports ``target`` at ``file:line``."""

    source: str
    target: str
    file: Path
    line: int


def module_name(package_dir: Path, file: Path) -> str:
    """The dotted name of the module ``file`` of the package at ``package_dir``."""
    parts = [package_dir.name, *file.relative_to(package_dir).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_modules(package_dir: Path) -> dict[str, Path]:
    """Every module of the package at ``package_dir``: dotted name -> file."""
    return {module_name(package_dir, file): file for file in sorted(package_dir.rglob("*.py"))}


def deepest_module(name: str, modules: dict[str, Path]) -> str | None:
    """The longest dotted prefix of ``name`` that is one of ``modules`` (None: none is)."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        prefix = ".".join(parts[:end])
        if prefix in modules:
            return prefix
    return None


def absolute_base(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` statement of ``module`` imports from."""
    if node.level == 0:
        return node.module or ""
    parts = module.split(".")
    package = parts if is_package else parts[:-1]
    base = package[:len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(module: str, file: Path, modules: dict[str, Path]) -> list[Import]:
    """Every import of one of ``modules`` by ``module`` (its file: ``file``), at any depth."""
    tree = ast.parse(file.read_text(encoding="utf-8"), filename=str(file))
    is_package = file.name == "__init__.py"
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = absolute_base(module, is_package, node)
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        else:
            continue
        for name in names:
            target = deepest_module(name, modules)
            if target is not None and target != module:
                found.append(Import(module, target, file, node.lineno))
    return sorted(set(found), key=lambda imp: (imp.line, imp.target))


def import_graph(package_dir: Path) -> dict[str, list[Import]]:
    """Module -> its imports of the package's modules, for every module of the package."""
    modules = package_modules(package_dir)
    return {name: imports_of(name, file, modules) for name, file in modules.items()}


def unit_of(module: str) -> str:
    """The top-level package or module (of the package) that ``module`` belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ROOT_UNIT


def layer_index(layers: tuple[tuple[str, ...], ...]) -> dict[str, int]:
    """Unit -> its layer's position in ``layers`` (0: the lowest)."""
    return {unit: i for i, layer in enumerate(layers) for unit in layer}


def unplaced_units(graph: dict[str, list[Import]], layers: tuple[tuple[str, ...], ...]) -> list[str]:
    """The units of ``graph``'s modules that no layer holds."""
    placed = layer_index(layers)
    return sorted({unit_of(m) for m in graph} - set(placed))


def layer_violations(graph: dict[str, list[Import]], layers: tuple[tuple[str, ...], ...],
                     same_layer: frozenset[tuple[str, str]] = frozenset(), root: Path | None = None) -> list[str]:
    """One line per import of a higher layer, or of another unit of the same layer that ``same_layer``
    does not allow, naming the importing file and line (relative to ``root`` when given)."""
    level = layer_index(layers)
    problems = []
    for imports in graph.values():
        for imp in imports:
            source, target = unit_of(imp.source), unit_of(imp.target)
            if source == target or source not in level or target not in level:
                continue
            if level[target] > level[source]:
                kind = "a higher layer"
            elif level[target] == level[source] and (source, target) not in same_layer:
                kind = "another unit of its own layer"
            else:
                continue
            where = imp.file.relative_to(root) if root is not None else imp.file
            problems.append(f"{where}:{imp.line}: {imp.source} (layer {level[source]}: {source}) imports "
                            f"{imp.target} ({kind}: layer {level[target]}: {target})")
    return problems


def strongly_connected(graph: dict[str, list[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of a directed graph (node -> successors), each sorted;
    iterative, so deep graphs do not reach the recursion limit."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(graph.get(start, ())))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            advanced = False
            for succ in successors:
                if succ not in index:
                    index[succ] = low[succ] = len(index)
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, iter(graph.get(succ, ()))))
                    advanced = True
                    break
                if succ in on_stack:
                    low[node] = min(low[node], index[succ])
            if advanced:
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                components.append(sorted(component))
    return components


def import_cycles(graph: dict[str, list[Import]], root: Path | None = None) -> list[str]:
    """One entry per set of modules that import each other round a circle, naming each import of
    the circle (file:line, relative to ``root`` when given)."""
    successors = {module: sorted({imp.target for imp in imports}) for module, imports in graph.items()}
    reports = []
    for component in strongly_connected(successors):
        if len(component) < 2:
            continue
        members = set(component)
        ties = [f"  {imp.file.relative_to(root) if root is not None else imp.file}:{imp.line}: "
                f"{imp.source} imports {imp.target}"
                for module in component for imp in graph[module] if imp.target in members]
        reports.append(f"circle of {', '.join(component)}:\n" + "\n".join(ties))
    return reports


# ---- the package ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def graph() -> dict[str, list[Import]]:
    return import_graph(PACKAGE_ROOT / PACKAGE)


def test_every_unit_has_a_layer(graph):
    assert not unplaced_units(graph, LAYERS), (
        f"units in no layer of LAYERS (place them there): {', '.join(unplaced_units(graph, LAYERS))}")


def test_the_layers_name_each_unit_once():
    units = [unit for layer in LAYERS for unit in layer]
    assert len(units) == len(set(units))


def test_imports_point_down_the_layers(graph):
    problems = layer_violations(graph, LAYERS, SAME_LAYER_IMPORTS, PACKAGE_ROOT)
    assert not problems, "imports against the layers of tests/test_layers.py:\n" + "\n".join(problems)


def test_no_import_cycles(graph):
    cycles = import_cycles(graph, PACKAGE_ROOT)
    assert not cycles, "modules that import each other:\n" + "\n".join(cycles)


# ---- the checker itself, on made-up packages ------------------------------------------------------
def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    package_dir = tmp_path / "pkg"
    for name, text in {"__init__.py": "", **files}.items():
        path = package_dir / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return package_dir


def test_the_checker_names_an_upward_import_inside_a_function(tmp_path):
    package_dir = _package(tmp_path, {
        "low.py": "import os\n\n\ndef f():\n    from pkg.high import g\n    return g\n",
        "high.py": "from pkg.low import f\n\n\ndef g():\n    return f\n",
    })
    graph = import_graph(package_dir)
    layers = ((ROOT_UNIT, "low"), ("high",))
    assert layer_violations(graph, layers, root=tmp_path) == [
        "pkg/low.py:5: pkg.low (layer 0: low) imports pkg.high (a higher layer: layer 1: high)"]
    assert layer_violations(graph, ((ROOT_UNIT, "high"), ("low",)), root=tmp_path) == [
        "pkg/high.py:1: pkg.high (layer 0: high) imports pkg.low (a higher layer: layer 1: low)"]
    # the two modules also import each other
    assert import_cycles(graph, tmp_path) == [
        "circle of pkg.high, pkg.low:\n  pkg/high.py:1: pkg.high imports pkg.low\n"
        "  pkg/low.py:5: pkg.low imports pkg.high"]


def test_the_checker_resolves_relative_imports_and_allows_only_listed_same_layer_imports(tmp_path):
    package_dir = _package(tmp_path, {
        "a/__init__.py": "from . import x\n",
        "a/x.py": "from ..b.y import thing\nfrom .z import other\n",
        "a/z.py": "import typing\n\nif typing.TYPE_CHECKING:\n    from pkg import c\n",
        "b/__init__.py": "",
        "b/y.py": "thing = 1\n",
        "c.py": "",
    })
    graph = import_graph(package_dir)
    assert {(i.source, i.target) for imports in graph.values() for i in imports} == {
        ("pkg.a", "pkg.a.x"), ("pkg.a.x", "pkg.b.y"), ("pkg.a.x", "pkg.a.z"), ("pkg.a.z", "pkg.c")}
    assert unplaced_units(graph, ((ROOT_UNIT, "a"),)) == ["b", "c"]
    layers = ((ROOT_UNIT, "c"), ("a", "b"))
    assert layer_violations(graph, layers, root=tmp_path) == [
        "pkg/a/x.py:1: pkg.a.x (layer 1: a) imports pkg.b.y (another unit of its own layer: layer 1: b)"]
    assert layer_violations(graph, layers, frozenset({("a", "b")})) == []
    assert import_cycles(graph) == []


def test_tarjan_finds_each_circle_once():
    graph = {"a": ["b"], "b": ["c"], "c": ["a", "d"], "d": ["e"], "e": ["d"], "f": ["f"], "g": []}
    assert sorted(strongly_connected(graph)) == [["a", "b", "c"], ["d", "e"], ["f"], ["g"]]
