"""The shape of the package (docs/design.md section 8): no import cycles, the model below its files."""

from __future__ import annotations

import ast
import json
import re
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
    """The rows of design section 8's concept table (docs/design/08-how-the-code-is-organised.md): (concept, files named)."""
    section = (PACKAGE.parent / "docs" / "design" / "08-how-the-code-is-organised.md").read_text()
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
    {"crfdepth.errors", "crfdepth._version", "crfdepth.lazy"},
    {"crfdepth.checks", "crfdepth.plausibility", "crfdepth.precision", "crfdepth.native"},
    {"crfdepth.config"},  # its groups check themselves with crfdepth.checks
    {"crfdepth.intrinsics", "crfdepth.layer_inputs"},
    {"crfdepth.geometry"},
    {"crfdepth.io", "crfdepth.metrics"},
    {"crfdepth.linalg", "crfdepth.superpixels", "crfdepth.weights"},
    {"crfdepth.fill", "crfdepth.sequences", "crfdepth.uncertainty"},
    {"crfdepth.potentials", "crfdepth.memory"},
    {"crfdepth.output"},
    {"crfdepth.inference"},
    {"crfdepth.model", "crfdepth.layer"},
    {"crfdepth.checkpoints", "crfdepth.inputs"},
    {"crfdepth.api"},
    {"crfdepth.pictures", "crfdepth.data"},
    {"crfdepth.runs"},
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


ROOT = PACKAGE.parent


def _exists(path: str) -> bool:
    """Whether ``path`` (from the repository root) is a folder, when it ends in /, or else a file."""
    return (ROOT / path).is_dir() if path.endswith("/") else (ROOT / path).is_file()


def _layout_entries(readme: str) -> list[tuple[str, str]]:
    """The Layout block of docs/layout.md as (path, description) pairs, paths relative to the repository.

    A line at indent 0 names a folder or file of the repository, one at indent 2 a file or
    folder inside the last indent-0 folder; a deeper line continues the description above."""
    block = readme[readme.index("```\n") + 4:]
    block = block[:block.index("```")]
    entries: list[tuple[str, str]] = []
    top = ""
    for line in block.splitlines():
        indent = len(line) - len(line.lstrip(" "))
        name, _, text = line.strip().partition(" ")
        if indent >= 4:
            entries[-1] = (entries[-1][0], entries[-1][1] + " " + line.strip())
            continue
        assert re.fullmatch(r"[\w.]+/?", name) and indent in (0, 2), line
        top = name if indent == 0 else top
        entries.append((name if indent == 0 else top + name, text.strip()))
    return entries


def _names_in(text: str) -> list[str]:
    """The files (``graph.py``, ``kitti.json``) and folders (``ros/``) a description names."""
    return re.findall(r"(?<![\w./])([\w/]*\w\.(?:py|json|md)\b|[a-z_]+/(?=[\s:),;]|$))", text)


def _layout_missing(readme: str) -> list[str]:
    missing = []
    for path, text in _layout_entries(readme):
        folder = path if path.endswith("/") else path[:path.rfind("/") + 1]  # a file's line names its neighbours
        missing += [name for name in [path] + [folder + n for n in _names_in(text)] if not _exists(name)]
    return missing


def test_every_path_the_layout_page_names_exists():
    readme = (ROOT / "docs" / "layout.md").read_text()
    paths = [path for path, _ in _layout_entries(readme)]
    for path in ("crfdepth/", "crfdepth/linalg/", "crfdepth/io/", "crfdepth/api.py", "train/", "tests/", "docs/"):
        assert path in paths, path
    packages = {f.parent.name + "/" for f in PACKAGE.glob("*/__init__.py")}
    assert {p.removeprefix("crfdepth/") for p in paths} >= packages, "a package the Layout does not list"
    assert not _layout_missing(readme), _layout_missing(readme)


def test_the_layout_check_finds_a_missing_file_and_a_missing_name_in_a_description():
    readme = (ROOT / "docs" / "layout.md").read_text()
    for old, new, found in [("\n  api.py ", "\n  apx.py ", "crfdepth/apx.py"),
                            ("(adjoint.py)", "(adjoin.py)", "crfdepth/linalg/adjoin.py"),
                            ("ros/:", "rox/:", "crfdepth/io/rox/")]:
        assert old in readme
        assert set(_layout_missing(readme.replace(old, new))) - set(_layout_missing(readme)) == {found}


def _paths_named(text: str) -> list[str]:
    """The ``crfdepth/...`` and ``tests/...`` paths a text names: files (.py, .md, .json) and folders."""
    return re.findall(r"(?<![\w/.])((?:crfdepth|tests)/[\w/.-]*?(?:\.(?:py|md|json)\b|/(?![\w.])))", text)


def test_every_crfdepth_and_tests_path_the_docs_and_code_name_exists():
    """README.md, docs/, notebooks' markdown cells and the comments and docstrings of crfdepth/,
    benchmarks/ and train/ name files by their path from the repository root."""
    texts = {str(p.relative_to(ROOT)): p.read_text() for p in
             [ROOT / "README.md", *ROOT.glob("docs/**/*.md"), *PACKAGE.rglob("*.py"),
              *ROOT.glob("benchmarks/*.py"), *ROOT.glob("train/*.py")]}
    for nb in ROOT.glob("notebooks/*.ipynb"):
        cells = json.loads(nb.read_text())["cells"]
        texts[str(nb.relative_to(ROOT))] = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "markdown")
    named = {(source, path) for source, text in texts.items() for path in _paths_named(text)}
    assert {path for _, path in named} >= {"tests/superpixels/test_slic.py", "crfdepth/linalg/system.py"}
    missing = sorted((source, path) for source, path in named if not _exists(path))
    assert not missing, missing


def test_the_path_finder_finds_files_and_folders_but_not_topics():
    text = "(`tests/test_slic.py`), crfdepth/io/ros/: the topic /crfdepth/depth, crfdepth/weights/kitti.json."
    assert _paths_named(text) == ["tests/test_slic.py", "crfdepth/io/ros/", "crfdepth/weights/kitti.json"]
    assert not _exists("tests/test_slic.py")
