"""The user-facing documents: README.md and the documentation pages under docs/, and their code blocks.

Tests read the commands, code and measured numbers from the documents themselves, so a page that
drifts from the code fails a test.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def page(name: str) -> str:
    """The text of ``README.md`` or of a page under docs/ (``"training.md"``, ``"reference/cli.md"``)."""
    path = ROOT / name if name == "README.md" else ROOT / "docs" / name
    return path.read_text(encoding="utf-8")


def code_blocks(language: str) -> list[tuple[str, int, str]]:
    """(document, index within it, code) of every fenced block of ``language`` in the documents."""
    out = []
    for path in DOCUMENTS:
        blocks = re.findall(rf"^```{language}\n(.*?)^```", path.read_text(encoding="utf-8"), flags=re.S | re.M)
        out += [(path.relative_to(ROOT).as_posix(), i + 1, block) for i, block in enumerate(blocks)]
    return out
