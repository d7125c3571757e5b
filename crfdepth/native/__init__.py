"""Optional compiled CPU kernels: the CG iteration in three fused passes, the affinities, the exact
nearest-return search in linear time and the predictive std in two passes (docs/design.md section 4b).

The eager torch path is the reference and always works; these kernels only do the same arithmetic
in fewer passes over memory. :func:`kernels` builds them on first use with the C++ compiler that
compiles Python extensions (``CXX``, else ``c++``), against the installed torch's headers, and
loads them; a later process loads the cached library directly (no compiler, no build tools
imported). Where nothing can be built (no compiler, no Python headers, another platform) the
eager path runs and one log line says so.

- First call: about 30 s of compiling (one translation unit), once per machine, torch release and
  source version.
- Cache: ``$CRFDEPTH_CACHE`` or ``~/.cache/crfdepth``, under ``kernels/<torch>-<python>-<source hash>/``.
- ``CRFDEPTH_NATIVE=0`` (or ``off``, ``false``, ``no``) turns them off: the eager path only.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.machinery
import importlib.util
import logging
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import warnings
from pathlib import Path
from types import ModuleType

import torch

__all__ = ["kernels", "enabled", "cache_dir", "eager"]

log = logging.getLogger("crfdepth")

_HERE = Path(__file__).parent
_SOURCES = [_HERE / "kernels.cpp"]  # the one translation unit: the module, including the other kernels (*.h)
_PARTS = sorted(_HERE.glob("*.h"))
_OFF = ("0", "off", "false", "no")
_state: dict[str, ModuleType | None] = {}
_eager_depth = [0]  # > 0 inside `with eager():`


def enabled() -> bool:
    """Whether the compiled kernels may be used (``CRFDEPTH_NATIVE`` is not set to off)."""
    return os.environ.get("CRFDEPTH_NATIVE", "1").strip().lower() not in _OFF


def cache_dir() -> Path:
    """Where built kernels are kept: ``$CRFDEPTH_CACHE/kernels``, else ``~/.cache/crfdepth/kernels``."""
    root = os.environ.get("CRFDEPTH_CACHE") or Path.home() / ".cache" / "crfdepth"
    return Path(root) / "kernels"


def _vector_flags() -> list[str]:
    """AVX2 and FMA where torch's own kernels found them on this CPU (``get_cpu_capability``); else the
    compiler's baseline, which runs on any CPU of the architecture."""
    capability = torch.backends.cpu.get_cpu_capability()
    if capability in ("AVX2", "AVX512"):  # at::vec's AVX2 vectors (torch's SLEEF log and exp) in predictive_std.h
        return ["-mavx2", "-mfma", "-DCPU_CAPABILITY=AVX2", "-DCPU_CAPABILITY_AVX2"]
    return ["-DCPU_CAPABILITY=DEFAULT"]


def _build_key() -> tuple[str, str]:
    source = b"".join(path.read_bytes() for path in [*_SOURCES, *_PARTS]) + " ".join(_vector_flags()).encode()
    digest = hashlib.sha256(source + torch.__version__.encode() + sys.version.encode()).hexdigest()[:12]
    tag = f"torch{torch.__version__.replace('+', '_')}-py{sys.version_info[0]}{sys.version_info[1]}-{digest}"
    return f"crfdepth_kernels_{digest}", tag


def _load(name: str, path: Path) -> ModuleType:
    loader = importlib.machinery.ExtensionFileLoader(name, str(path))
    spec = importlib.util.spec_from_file_location(name, str(path), loader=loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def _compile(name: str, target: Path) -> None:
    """Compile the kernels into ``target`` (written under another name, then renamed: a build that
    fails or is interrupted leaves nothing a later process would load)."""
    compiler = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        raise RuntimeError("no C++ compiler (set CXX, or install g++)")
    include = Path(torch.__file__).parent / "include"
    lib = Path(torch.__file__).parent / "lib"
    python_include = sysconfig.get_paths()["include"]
    if not (Path(python_include) / "Python.h").exists():
        raise RuntimeError(f"no Python headers under {python_include}")
    abi = int(torch._C._GLIBCXX_USE_CXX11_ABI)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    command = [compiler, "-O3", *_vector_flags(), "-shared", "-fPIC", "-std=c++17", "-fopenmp", "-fno-math-errno", "-fno-trapping-math", "-w", *map(str, _SOURCES), "-o", tmp,
               f"-I{include}", f"-I{include / 'torch' / 'csrc' / 'api' / 'include'}", f"-I{python_include}",
               f"-D_GLIBCXX_USE_CXX11_ABI={abi}", f"-DTORCH_EXTENSION_NAME={name}", "-DTORCH_API_INCLUDE_EXTENSION_H",
               f"-L{lib}", "-lc10", "-ltorch", "-ltorch_cpu", "-ltorch_python", f"-Wl,-rpath,{lib}"]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=600)
        if done.returncode != 0:
            lines = done.stderr.strip().splitlines() or ["no message"]
            first = next((line for line in lines if "error" in line), lines[-1])
            raise RuntimeError(f"the compiler failed: {first.strip()[:200]}")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _build_or_load() -> ModuleType | None:
    if not enabled():
        return None
    if sys.platform != "linux" and sys.platform != "darwin":
        log.warning("crfdepth: compiled CPU kernels are built on Linux and macOS only; using the eager torch path")
        return None
    name, tag = _build_key()
    target = cache_dir() / tag / f"{name}.so"
    try:
        if not target.exists():
            log.warning("crfdepth: building its compiled CPU kernels once (under a minute) into %s", target.parent)
            _compile(name, target)
        return _load(name, target)
    except Exception as err:  # any failure to build or load: the eager path is always there
        log.warning("crfdepth: compiled CPU kernels unavailable (%s); using the eager torch path "
                    "(set CRFDEPTH_NATIVE=0 to skip trying)", err)
        return None


@contextlib.contextmanager
def eager():
    """Inside this block :func:`kernels` returns None: the eager torch path runs (the tests' reference)."""
    _eager_depth[0] += 1
    try:
        yield
    finally:
        _eager_depth[0] -= 1


class _Guarded:
    """The kernels' module, each function of which returns None instead of raising: a kernel that fails at run
    time (a bug, an unexpected input) is told in one warning, the kernels are off for the rest of the process, and
    the caller runs the eager path (every caller treats None so)."""

    def __init__(self, module: ModuleType) -> None:
        self._module = module

    def __repr__(self) -> str:
        return f"<crfdepth.native kernels {self._module.__file__}>"

    def __getattr__(self, name: str):
        function = getattr(self._module, name)

        def guarded(*args):
            if _state.get("module") is not self:  # turned off after a failure: said once already
                return None
            try:
                return function(*args)
            except Exception as err:  # the eager path gives the answer; never a traceback from here
                first = (str(err).strip().splitlines() or [type(err).__name__])[0]
                warnings.warn(f"crfdepth: the compiled kernel {name} failed ({first[:200]}); the eager torch path "
                              "runs instead, for the rest of this process", RuntimeWarning, stacklevel=2)
                _state["module"] = None
                return None

        return guarded


def kernels() -> _Guarded | None:
    """The compiled kernels (:class:`_Guarded`), built or loaded on the first call; None where they cannot be
    had (then the eager path runs; the reason is logged once), after one failed at run time, and inside
    :func:`eager`."""
    if _eager_depth[0]:
        return None
    if "module" not in _state:
        module = _build_or_load()
        _state["module"] = None if module is None else _Guarded(module)
    return _state["module"]
