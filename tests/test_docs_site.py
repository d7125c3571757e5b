"""The documentation site (mkdocs.yml, docs/): it builds in strict mode, and its reference pages follow the code.

One ``mkdocs build --strict`` per session, shared by the tests. The command-line reference is generated
from the argparse parsers by docs/hooks.py and the API pages from the docstrings by mkdocstrings; the
tests read the expected text from the parsers and the objects, not from a list kept here.
"""

from __future__ import annotations

import argparse
import html
import importlib.util
import inspect
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from crfdepth.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOC_TOOLS = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")


def _text(path: Path) -> str:
    """The visible text of a built HTML page: tags dropped, entities unescaped, whitespace runs as one space."""
    page = path.read_text(encoding="utf-8")
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", page)).split())


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built from mkdocs.yml with ``--strict`` (any warning fails the build)."""
    missing = [name for name in DOC_TOOLS if importlib.util.find_spec(name.split(".")[0]) is None
               or importlib.util.find_spec(name) is None]
    if missing:
        if os.environ.get("CI"):  # CI installs crfdepth[test], which holds the docs tools
            pytest.fail(f"documentation tools not installed: {missing}")
        pytest.skip(f"documentation tools not installed: {missing} (pip install crfdepth[docs])")
    out = tmp_path_factory.mktemp("docs") / "site"
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    return out


def _commands() -> dict[str, argparse.ArgumentParser]:
    """``crfdepth`` and its sub-commands by program name ("crfdepth", "crfdepth demo", ...)."""
    parser = build_parser()
    found = {parser.prog: parser}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found.update({sub.prog: sub for sub in action.choices.values()})
    return found


def test_site_builds_strictly(site):
    assert (site / "index.html").is_file()
    assert (site / "reference" / "cli" / "index.html").is_file()
    assert (site / "reference" / "api" / "index.html").is_file()


def test_cli_reference_holds_every_command_and_option(site):
    """Each command's section (from its ``usage:`` line to the next) names all of its options."""
    text = _text(site / "reference" / "cli" / "index.html")
    commands = _commands()
    assert set(commands) >= {f"crfdepth {name}" for name in ("demo", "project", "complete", "evaluate", "targets")}
    starts = {}
    for prog in commands:
        found = re.search(rf"usage: {re.escape(prog)} \[", text)
        assert found, f"no usage line of {prog!r} on the command-line reference page"
        starts[prog] = found.start()
    bounds = sorted(starts.values()) + [len(text)]
    for prog, parser in commands.items():
        section = text[starts[prog]:bounds[bounds.index(starts[prog]) + 1]]
        options = [option for action in parser._actions for option in action.option_strings]
        assert options, prog
        missing = [option for option in options if not re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", section)]
        assert not missing, f"{prog}: options missing from the command-line reference: {missing}"


def test_cli_reference_fits_the_page_and_wraps_rather_than_scrolls(site):
    """Every help line fits 72 columns (the theme's text column on a laptop), and the blocks wrap on a narrower
    window: the page's stylesheet sets ``white-space: pre-wrap`` on them, so no option hides behind a scrollbar."""
    page = (site / "reference" / "cli" / "index.html").read_text(encoding="utf-8")
    blocks = re.findall(r'<pre class="cli-help"><code>(.*?)</code></pre>', page, flags=re.S)
    assert len(blocks) == len(_commands())
    long = [line for block in blocks for line in html.unescape(block).splitlines() if len(line) > 72]
    assert not long, f"{len(long)} help lines over 72 columns, e.g. {long[0]!r}"
    assert 'href="../../stylesheets/cli.css"' in page
    css = (site / "stylesheets" / "cli.css").read_text()
    assert re.search(r"pre\.cli-help > code \{[^}]*white-space: pre-wrap", css)


def test_api_reference_holds_the_model_and_its_docstring(site):
    from crfdepth.api import complete_depth
    from crfdepth.model import CRFDepth

    text = _text(site / "reference" / "api" / "index.html")
    for name in ("CRFDepth", "forward", "from_pretrained", "complete_depth", "crf_refine", "load_model"):
        assert name in text, f"{name} missing from the Python API page"
    for obj in (CRFDepth, complete_depth):
        summary = " ".join(inspect.getdoc(obj).split("\n\n")[0].replace("``", "").split())
        assert summary in text, f"the first line of {obj.__name__}'s docstring is missing: {summary!r}"
