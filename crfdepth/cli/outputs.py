"""Output folders and files of the commands, checked before any computation and written atomically.

- :func:`make_output_dir` / :func:`check_writable_dir` / :func:`same_file`: output paths
  named by their flag (a file is actually created in the folder and removed,
  :func:`crfdepth.io.files.probe_folder`); output files are checked with
  :func:`crfdepth.io.files.check_output_file`;
- :func:`check_output_folders` / :func:`output_folders`: the output folders of the folder
  and bag modes, checked up front (another run writing there is refused at once), then
  created and locked for the run (:func:`crfdepth.io.files.lock_folder`);
- :func:`write_frame` / :func:`write_pictures` / :func:`write_rgb_png`: a completed frame's
  PNGs and pictures.
"""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes, check_not_locked, lock_folder, probe_folder
from crfdepth.io.kitti import write_depth_png
from crfdepth.pictures.figures import depth_picture, std_picture

__all__ = ["check_output_folders", "check_writable_dir", "make_output_dir", "output_folders", "same_file",
           "write_frame", "write_pictures", "write_rgb_png"]

_MIN_DEPTH = 1.0 / 256.0  # smallest non-zero code of a KITTI depth PNG, metres


def check_writable_dir(directory: Path, what: str) -> None:
    """An existing folder where a file can be created (named ``what`` in the error): a hidden file is
    created there and removed (:func:`crfdepth.io.files.probe_folder`), since permission bits do not
    bind root and ``/proc`` or ``/sys`` refuse new files whatever ``os.access`` says."""
    if not directory.is_dir():
        raise FileNotFoundError(f"{what}: output folder does not exist: {directory}")
    problem = probe_folder(directory)
    if problem is not None:
        raise PermissionError(f"{what}: output folder is not writable: {directory} (creating a file there "
                              f"fails: {problem})")


def make_output_dir(path: str | Path, what: str) -> Path:
    """An output folder, created (with parents) if missing; must be writable."""
    directory = Path(path)
    if directory.exists() and not directory.is_dir():
        raise InputError(f"{what}: expected a folder, got a file: {directory}")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PermissionError(f"{what}: cannot create output folder {directory}: {exc.strerror}") from None
    check_writable_dir(directory, what)
    return directory


def check_output_folders(args: argparse.Namespace, inputs: list[Path], source: str) -> list[tuple[str, str | None]]:
    """The ``--out-dir``, ``--out-std-dir`` and ``--vis`` folders of the folder and bag modes as ``(flag, folder)``
    (``--vis`` only when given; a bare ``--vis`` is ``<out-dir>_vis``), refused when one is among ``inputs``
    (named ``source`` in the message), two are the same folder, one is a file, the folder (or, for one to be
    created, the nearest existing folder above it) does not take new files, or another crfdepth run holds
    it locked. Nothing is created (a probe file is created and removed)."""
    targets = [("--out-dir", args.out_dir), ("--out-std-dir", args.out_std_dir)]
    if args.vis is not None:
        targets.append(("--vis", args.vis or f"{Path(args.out_dir).resolve()}_vis"))
    for flag, value in targets:
        if value is not None and any(same_file(value, p) for p in inputs):
            raise InputError(f"{flag}: {value} is {source}; refusing to write there")
    resolved = [os.path.realpath(v) for _, v in targets if v is not None]
    if len(set(resolved)) != len(resolved):
        raise InputError("--out-dir, --out-std-dir and --vis: expected different folders")
    for flag, value in targets:
        if value is None:
            continue
        folder = Path(value)
        if folder.exists() and not folder.is_dir():
            raise InputError(f"{flag}: expected a folder, got a file: {folder}")
        # the folder, or the nearest one above it that exists (the run creates the rest), must take new files
        existing = next((p for p in (folder, *folder.absolute().parents) if p.is_dir()), None)
        if existing is not None:
            check_writable_dir(existing, flag)
        check_not_locked(folder, flag)  # another run writes there: refused now, not after the checks
    return targets


@contextlib.contextmanager
def output_folders(targets: list[tuple[str, str | None]]) -> Iterator[list[Path | None]]:
    """The ``(flag, folder)`` targets of :func:`check_output_folders`, created (:func:`make_output_dir`) and
    locked (:func:`crfdepth.io.files.lock_folder`) for the ``with`` block; yields their paths (None where not
    given). On leaving the block the locks are released, and a folder this run created that is still
    empty (nothing was written: an error or Ctrl-C before the first frame) is removed again."""
    created: list[Path] = []
    with contextlib.ExitStack() as stack:
        try:
            folders: list[Path | None] = []
            for flag, value in targets:
                if value is None:
                    folders.append(None)
                    continue
                existed = Path(value).is_dir()
                folder = make_output_dir(value, flag)
                if not existed:
                    created.append(folder)
                stack.enter_context(lock_folder(folder, flag))
                folders.append(folder)
            yield folders
        finally:
            stack.close()  # the locks first, so that an empty folder is empty
            for folder in reversed(created):
                with contextlib.suppress(OSError):
                    folder.rmdir()  # only succeeds when empty


def same_file(a: Path, b: Path) -> bool:
    return os.path.realpath(a) == os.path.realpath(b)


def write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB picture as PNG, atomically (temporary file + rename)."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - cv2 encodes any uint8 HxWx3 array
        raise InputError(f"vis: could not encode a picture of shape {rgb.shape} as PNG")
    atomic_write_bytes(path, encoded.tobytes())


def write_pictures(folder: Path, stem: str, depth: np.ndarray, std: np.ndarray | None,
                   vis_range: tuple[float, float] | None) -> list[Path]:
    """``<stem>_vis_depth.png`` and ``<stem>_vis_std.png`` with colour bars in metres (atomic writes).

    ``vis_range`` fixes the depth colour scale (metres) for every frame of a sequence.
    """
    if vis_range is not None and not vis_range[0] < vis_range[1]:
        raise InputError(f"--vis-range: expected MIN < MAX, got {vis_range[0]:g} {vis_range[1]:g}")
    written = [folder / f"{stem}_vis_depth.png"]
    write_rgb_png(written[0], depth_picture(depth, vis_range=vis_range))
    if std is not None:
        written.append(folder / f"{stem}_vis_std.png")
        write_rgb_png(written[1], std_picture(std))
    return written


def write_frame(depth: np.ndarray, std: np.ndarray | None, out: Path, out_std: Path | None,
                vis_dir: Path | None, stem: str, vis_range) -> list[Path]:
    """A frame's depth PNG (and std PNG, and pictures into ``vis_dir``), each written atomically; returns the paths.
    PNG values are clipped below at 1/256 m so that no pixel reads as "no value"."""
    if not np.all(np.isfinite(depth)):
        raise InputError(f"{stem}: the model returned {int(np.sum(~np.isfinite(depth)))} non-finite "
                         f"depth value(s); nothing written")
    write_depth_png(out, np.maximum(depth, _MIN_DEPTH))
    written = [out]
    if out_std is not None:
        write_depth_png(out_std, np.maximum(np.nan_to_num(std, nan=_MIN_DEPTH), _MIN_DEPTH))
        written.append(out_std)
    if vis_dir is not None:
        written += write_pictures(vis_dir, stem, depth, std, vis_range)
    return written
