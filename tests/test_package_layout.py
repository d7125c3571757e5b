"""The shape of the package (docs/design.md section 8): no import cycles, the model below its files."""

from __future__ import annotations

import ast
from pathlib import Path

import crfdepth

PACKAGE = Path(crfdepth.__file__).resolve().parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_lines(tree: ast.Module) -> set[int]:
    lines = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                lines.update(range(child.lineno, child.end_lineno + 1))
    return lines


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The crfdepth modules importing ``path`` runs, at any depth of the file (a function's lazy
    import runs too, when the function does), with the package ``__init__`` each one runs."""
    tree = ast.parse(path.read_text())
    skip = _type_checking_lines(tree)
    this = _module_name(path)
    names = set()
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    found = set()
    for name in names:
        parts = name.split(".")
        for i in range(1, len(parts) + 1):  # importing a.b.c runs a/__init__, a/b/__init__ and a/b/c
            prefix = ".".join(parts[:i])
            if prefix in modules and prefix != this and not this.startswith(prefix + "."):
                found.add(prefix)
    return found


def _graph() -> dict[str, set[str]]:
    files = sorted(PACKAGE.rglob("*.py"))
    modules = {_module_name(f) for f in files}
    return {_module_name(f): _imports(f, modules) for f in files}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_no_import_cycle_counting_package_inits_and_lazy_imports():
    graph = _graph()
    assert len(graph) > 60 and "crfdepth.superpixels.slic" in graph
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


def test_cycle_finder_finds_a_planted_cycle():
    graph = _graph()
    graph["crfdepth.linalg.cg"] = graph["crfdepth.linalg.cg"] | {"crfdepth.model"}
    assert _cycle(graph) is not None


def test_the_model_builds_from_files_without_the_functions_that_build_it():
    """crfdepth.model loads through crfdepth.weights (formats and checks, no model); the
    functions that need the model (crfdepth.checkpoints) sit above it."""
    graph = _graph()
    below_model = {"crfdepth.weights", "crfdepth.weights.files", "crfdepth.weights.state"}
    assert below_model <= graph["crfdepth.model"] | {"crfdepth.weights.files", "crfdepth.weights.state"}
    assert all("crfdepth.model" not in graph[m] and "crfdepth.checkpoints" not in graph[m] for m in below_model)
    assert "crfdepth.model" in graph["crfdepth.checkpoints"]


def _concept_table() -> list[tuple[str, list[str]]]:
    """The rows of docs/design.md section 8's concept table: (concept, files named)."""
    import re

    text = (PACKAGE.parent / "docs" / "design.md").read_text()
    section = text[text.index("## 8. How the code is organised"):text.index("## 9.")]
    rows = [line for line in section.splitlines() if line.startswith("| ") and not line.startswith("| concept")]
    return [(row.split("|")[1].strip(), re.findall(r"`([\w/.]+\.py)`", row.split("|")[2])) for row in rows]


def test_every_file_the_concept_table_names_exists():
    rows = _concept_table()
    assert len(rows) >= 30 and all(files for _, files in rows), rows
    missing = [(concept, f) for concept, files in rows for f in files if not (PACKAGE.parent / f).is_file()]
    assert not missing, missing


def test_the_concept_table_covers_the_paper_and_its_additions():
    concepts = " ".join(concept for concept, _ in _concept_table()).lower()
    for word in ("superpixels", "data term", "affinities", "normals", "conjugate gradient", "posterior variance",
                 "predictive", "count-based", "occlusion gate", "ip-basic", "head", "photometric", "targets"):
        assert word in concepts, word


LAYERS = [  # bottom first (docs/design.md section 8); a module imports only its own package or lower layers
    {"crfdepth.errors", "crfdepth._version"},
    {"crfdepth.checks", "crfdepth.plausibility", "crfdepth.config", "crfdepth.precision"},
    {"crfdepth.io", "crfdepth.metrics"},
    {"crfdepth.geometry", "crfdepth.linalg", "crfdepth.superpixels", "crfdepth.weights"},
    {"crfdepth.fill", "crfdepth.sequences", "crfdepth.uncertainty"},
    {"crfdepth.potentials", "crfdepth.memory"},
    {"crfdepth.output"},
    {"crfdepth.inference"},
    {"crfdepth.model", "crfdepth.layer"},
    {"crfdepth.checkpoints", "crfdepth.inputs"},
    {"crfdepth.api"},
    {"crfdepth.pictures", "crfdepth.data"},
    {"crfdepth.cli"},
    {"crfdepth", "crfdepth.__main__"},
]


def _group(module: str) -> str:
    return ".".join(module.split(".")[:2])


def test_every_module_imports_only_its_own_package_or_layers_below():
    layer = {name: i for i, names in enumerate(LAYERS) for name in names}
    graph = _graph()
    unplaced = sorted({_group(m) for m in graph} - set(layer))
    assert not unplaced, f"packages without a layer: {unplaced}"
    upward = sorted(f"{m} -> {d}" for m, deps in graph.items() for d in deps
                    if _group(m) != _group(d) and layer[_group(d)] >= layer[_group(m)])
    assert not upward, upward


def test_no_module_is_over_400_lines():
    long = {str(f.relative_to(PACKAGE.parent)): n for f in PACKAGE.rglob("*.py")
            if (n := len(f.read_text().splitlines())) > 400}
    assert not long, long
