"""Start-up: a command imports only what it uses (issue 48). Properties of ``sys.modules``, not timings
(benchmarks/startup.py times them), each checked in a fresh interpreter."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# Heavy modules no start-up path below needs (torch alone is most of a second).
HEAVY = ("torch", "scipy", "skimage", "kornia", "cv2", "lightning", "rerun", "rosbags", "kiss_icp", "matplotlib",
         "plyfile", "pypcd4")


def _loaded_after(code: str) -> tuple[list[str], str]:
    """The modules of HEAVY that running ``code`` in a fresh interpreter imported, and its stdout."""
    script = (f"import json, sys\n{code}\n"
              f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    return json.loads(lines[-1]), "\n".join(lines[:-1])


def test_import_crfdepth_imports_no_heavy_module():
    assert _loaded_after("import crfdepth") == ([], "")


def test_import_crfdepth_cli_imports_no_heavy_module():
    assert _loaded_after("import crfdepth.cli") == ([], "")


def test_version_imports_no_heavy_module():
    loaded, out = _loaded_after("from crfdepth.cli import main\ntry:\n    main(['--version'])\n"
                                "except SystemExit as exc:\n    assert exc.code == 0, exc.code")
    assert loaded == []
    assert out.startswith("crfdepth ")


@pytest.mark.parametrize("name", ["CRFDepth", "complete_depth", "crf_refine", "CRFRefine"])
def test_the_public_api_is_there_at_first_use(name):
    loaded, out = _loaded_after(f"import crfdepth\nfrom crfdepth import {name}\nprint({name}.__module__)")
    assert "torch" in loaded  # imported now, at first use
    assert out.startswith("crfdepth.")


def test_a_sub_command_imports_only_its_own_module():
    code = ("from crfdepth.cli import main\ntry:\n    main(['project', '--help'])\n"
            "except SystemExit as exc:\n    assert exc.code == 0, exc.code\n"
            "print(sorted(m for m in sys.modules if m.startswith('crfdepth.cli.') and m.count('.') == 2))")
    loaded, out = _loaded_after(code)
    modules = out.strip().splitlines()[-1]
    for other in ("demo", "complete", "evaluate", "targets"):
        assert f"'crfdepth.cli.{other}'" not in modules, modules
    assert "'crfdepth.cli.project'" in modules
    assert not {"lightning", "rerun", "rosbags", "kiss_icp", "matplotlib"} & set(loaded)


def test_help_lists_every_command_and_imports_no_optional_heavy_module():
    loaded, out = _loaded_after("from crfdepth.cli import main\ntry:\n    main(['--help'])\n"
                                "except SystemExit as exc:\n    assert exc.code == 0, exc.code")
    for command in ("demo", "project", "complete", "evaluate", "targets"):
        assert f"    {command}" in out, command
    assert not {"lightning", "rerun", "rosbags", "kiss_icp", "matplotlib"} & set(loaded)


def test_build_parser_of_one_command_gives_the_same_sub_parser():
    from crfdepth.cli import build_parser

    full, one = build_parser(), build_parser(("project",))
    assert set(one.commands) == {"project"}
    assert one.commands["project"].format_help() == full.commands["project"].format_help()


def test_an_eager_forward_never_imports_the_compiler():
    """torch._dynamo costs about a second of import: only a forward under torch.compile loads it (the CRF's part
    of the forward is kept out of compiled graphs lazily, crfdepth.model._eager_forward)."""
    code = ("import sys, torch\nfrom crfdepth import CRFDepth\nfrom crfdepth.data.synthetic import make_scene\n"
            "s = make_scene(seed=0).to_tensors()\n"
            "with torch.inference_mode():\n"
            "    CRFDepth.from_pretrained()(s['image'][None], s['sparse'][None], s['K'][None], return_std=True)\n"
            "print('torch._dynamo' in sys.modules)")
    _, out = _loaded_after(code)
    assert out == "False"


def test_the_default_models_forward_imports_neither_kornia_nor_scipy():
    """The pixel grid's forward (and the metrics' module) needs neither: their imports cost 0.2 s and 0.5 s of a
    fresh process's first frame (benchmarks/startup.py). Where the compiled kernels are off, the eager fill and std
    use SciPy and OpenCV, so this runs with the kernels as the process has them."""
    code = ("import sys, torch\nfrom crfdepth import CRFDepth, native\nimport crfdepth.metrics, crfdepth.io.files\n"
            "from crfdepth.data.synthetic import make_scene\n"
            "s = make_scene(seed=0).to_tensors()\n"
            "with torch.inference_mode():\n"
            "    CRFDepth.from_pretrained()(s['image'][None], s['sparse'][None], s['K'][None], return_std=True)\n"
            "print(native.kernels() is not None)")
    loaded, out = _loaded_after(code)
    assert "kornia" not in loaded and "pypcd4" not in loaded
    if out == "True":  # the kernels' fill needs no SciPy
        assert "scipy" not in loaded
