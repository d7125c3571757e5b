"""Every Python block of README.md runs as pasted (the blocks are read from README.md itself)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCKS = re.findall(r"^```python\n(.*?)^```", (ROOT / "README.md").read_text(), flags=re.S | re.M)


def test_readme_has_python_blocks():
    assert len(BLOCKS) >= 4


@pytest.mark.parametrize("index", range(len(BLOCKS)), ids=lambda i: f"block{i + 1}")
def test_readme_python_block_runs(index, monkeypatch):
    monkeypatch.chdir(ROOT)  # the README's relative paths (docs/example/...) are from the repository root
    namespace = {"__name__": f"readme_block{index + 1}"}
    exec(compile(BLOCKS[index], f"README.md python block {index + 1}", "exec"), namespace)
