"""Every Python block of README.md and of the documentation pages runs as pasted (read from the files themselves)."""

import pytest

from tests.documents import ROOT, code_blocks

BLOCKS = code_blocks("python")


def test_the_documents_have_python_blocks():
    documents = {document for document, _, _ in BLOCKS}
    assert {"README.md", "docs/getting-started.md", "docs/own-sensors.md", "docs/layer.md"} <= documents


@pytest.mark.parametrize("document, index, code", BLOCKS, ids=[f"{d}:block{i}" for d, i, _ in BLOCKS])
def test_python_block_runs(document, index, code, monkeypatch):
    monkeypatch.chdir(ROOT)  # the documents' relative paths (docs/example/...) are from the repository root
    namespace = {"__name__": f"{document}_block{index}"}
    exec(compile(code, f"{document} python block {index}", "exec"), namespace)
