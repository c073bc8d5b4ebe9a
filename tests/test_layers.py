"""The package's layers run one way, and the stages and DataModules live inside the threedq namespace.

Layers (``docs/architecture.md``), lowest first; a module may import from its own layer or below, never
above, and no two modules may import each other through any chain (function-local imports included):

    core      threedq.{atomic_io, locks, boxes, scene, geometry, nets, quantization, contrastive, metrics, baselines,
              proposals, box_refinement, data}
    stages    threedq.stages, threedq.datamodules
    pipeline  threedq.pipeline
    entry     threedq.cli, threedq.__main__
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import threedq

ROOT = Path(__file__).resolve().parents[1]
#: package -> folder in the source tree (stages/ and datamodules/ sit at the top, installed inside threedq)
SOURCES = {"threedq": ROOT / "threedq", "threedq.stages": ROOT / "stages", "threedq.datamodules": ROOT / "datamodules"}
#: these tests read the source tree; the Docker image holds the installed package and the tests only
needs_sources = pytest.mark.skipif(not (ROOT / "threedq" / "__init__.py").is_file(),
                                   reason="reads the source tree, which this install does not hold (e.g. the Docker image)")
LAYERS = {"core": 0, "stages": 1, "pipeline": 2, "entry": 3}


def layer_of(module: str) -> str:
    if module in ("threedq.cli", "threedq.__main__"):
        return "entry"
    if module == "threedq.pipeline" or module.startswith("threedq.pipeline."):
        return "pipeline"
    if module.startswith(("threedq.stages", "threedq.datamodules")):
        return "stages"
    return "core"


def modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for package, folder in SOURCES.items():
        for f in sorted(folder.rglob("*.py")):
            rel = f.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([package, *parts])
            if package == "threedq" and parts and parts[0] in ("stages", "datamodules", "configs"):
                continue
            out[name] = f
    return out


def imports_of(module: str, path: Path, known: set[str]) -> set[str]:
    """threedq modules imported anywhere in ``path`` (top level, functions, TYPE_CHECKING blocks alike)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        for n in names:
            # the longest known module that n names (a submodule, or the module a name is imported from)
            while n and n not in known:
                n = n.rpartition(".")[0]
            if n and n != module:
                found.add(n)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    mods = modules()
    known = set(mods)
    return {m: imports_of(m, p, known) for m, p in mods.items()}


@needs_sources
def test_no_top_level_stages_or_datamodules_in_source_tree() -> None:
    # every import names the installed path
    offenders = []
    for m, p in modules().items():
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] in ("stages", "datamodules"):
                offenders.append(f"{p}:{node.lineno}")
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] in ("stages", "datamodules") for a in node.names):
                offenders.append(f"{p}:{node.lineno}")
    assert not offenders, offenders


@needs_sources
def test_layers_run_one_way(graph: dict[str, set[str]]) -> None:
    back = [
        f"{m} ({layer_of(m)}) imports {d} ({layer_of(d)})"
        for m, deps in graph.items() for d in deps if LAYERS[layer_of(d)] > LAYERS[layer_of(m)]
    ]
    assert not back, "back edges:\n" + "\n".join(sorted(back))


@needs_sources
def test_no_import_cycles(graph: dict[str, set[str]]) -> None:
    # a package's __init__ re-exporting its submodules is not a cycle of the design: drop parent -> child edges
    edges = {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(edges.get(m, ())):
            if state.get(d) == 1:
                cycles.append(" -> ".join([*stack[stack.index(d):], d]))
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


@needs_sources
def test_the_graph_is_not_empty(graph: dict[str, set[str]]) -> None:
    # guards the walk itself: a parser that found nothing would pass the tests above
    assert "threedq.stages.base" in graph and "threedq.geometry" in graph["threedq.stages.base"]
    assert "threedq.pipeline.lightning_cli" in graph["threedq.pipeline.em"]
    assert layer_of("threedq.pipeline.em") == "pipeline" and layer_of("threedq.datamodules.scene_folder") == "stages"


def test_a_back_edge_is_caught(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from threedq.pipeline.em import run_em\n")
    deps = imports_of("threedq.geometry.bad", bad, {"threedq.pipeline.em", "threedq.pipeline"})
    assert deps == {"threedq.pipeline.em"} and layer_of("threedq.pipeline.em") == "pipeline"


@pytest.mark.parametrize("name", ["stages", "datamodules"])
def test_no_top_level_package_after_install(name: str, tmp_path: Path) -> None:
    # run outside the repository, so that the working directory cannot put the source folders on sys.path
    code = f"import importlib.util, threedq.{name}; print(importlib.util.find_spec({name!r}) is None)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"


def test_stages_are_inside_the_namespace() -> None:
    import threedq.datamodules.scene_folder as sf
    import threedq.stages.viewpred as vp

    if (ROOT / "threedq" / "__init__.py").is_file():  # the checkout (editable install): the folders at the top
        assert Path(vp.__file__).resolve().parent == (ROOT / "stages").resolve()
        assert Path(sf.__file__).resolve().parent == (ROOT / "datamodules").resolve()
        assert Path(threedq.__file__).resolve().parent == (ROOT / "threedq").resolve()
    else:  # a wheel (the Docker image): installed inside the package
        package = Path(threedq.__file__).resolve().parent
        assert Path(vp.__file__).resolve().parent == package / "stages"
        assert Path(sf.__file__).resolve().parent == package / "datamodules"
