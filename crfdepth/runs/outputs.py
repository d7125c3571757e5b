"""Output folders and files of the runs and commands, checked before any computation and written atomically.

- :func:`make_output_dir` / :func:`check_writable_dir` / :func:`same_file`: output paths
  named by their flag (a file is actually created in the folder and removed,
  :func:`crfdepth.io.files.probe_folder`); output files are checked with
  :func:`crfdepth.io.files.check_output_file`;
- :func:`check_output_folders` / :func:`output_folders`: the output folders of the folder
  and bag modes, checked up front (another run writing there is refused at once), then
  created and locked for the run (:func:`crfdepth.io.files.lock_folder`);
- :func:`write_files` / :func:`write_frame` / :func:`write_pictures` / :func:`write_rgb_png`: a
  completed frame's PNGs and pictures, and the commands' other files;
- :func:`rerun_recording`: the Rerun recording of ``--rerun`` (:mod:`crfdepth.pictures.rerun_recording`).

Errors name the flag the caller gives for each path (``--out-dir``, ``--vis`` ...): the command line's
names, which the library's runs keep (docs/design.md section 8).

Every file is written to a temporary file beside it (``.crfdepth-<random>.tmp``) and renamed over
it only when complete; the files of one frame are renamed only when all of them are written, and a
failure removes those already renamed (:func:`write_files`): a failed or interrupted write leaves
neither a partial file nor part of a frame. The error names the user's flag and the file asked for,
never the temporary file (``--out: cannot write d/depth.png: No space left on device``,
:class:`~crfdepth.io.file_errors.FileError`).
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.file_errors import cannot_write, flagged
from crfdepth.io.files import check_not_locked, check_output_file, lock_folder, probe_folder
from crfdepth.io.kitti import depth_png_codes
from crfdepth.pictures.figures import depth_picture, std_picture
from crfdepth.pictures.rerun_recording import Recorder, import_rerun, open_recording

__all__ = ["check_output_folder", "check_output_folders", "check_writable_dir", "make_output_dir", "output_folders",
           "is_inside", "rerun_recording", "same_file", "write_depth_png", "write_files", "write_frame", "write_pictures",
           "write_rgb_png"]

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
    with flagged(what, directory, "write"):
        if directory.exists() and not directory.is_dir():
            raise InputError(f"{what}: expected a folder, got a file: {directory}")
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PermissionError(f"{what}: cannot create output folder {directory}: {exc.strerror}") from None
        check_writable_dir(directory, what)
    return directory


def check_output_folders(out_dir: str, out_std_dir: str | None, vis: str | None, inputs: list[Path], source: str
                         ) -> list[tuple[str, str | None]]:
    """The ``--out-dir``, ``--out-std-dir`` and ``--vis`` folders of the folder and bag modes as ``(flag, folder)``
    (``--vis`` only when ``vis`` is not None; ``""``, a bare ``--vis``, is ``<out-dir>_vis``), refused when one is
    one of ``inputs`` or inside one (named ``source`` in the message: the run would write among its inputs),
    two are the same folder, one is a file, the folder (or, for one to be
    created, the nearest existing folder above it) does not take new files, or another crfdepth run holds
    it locked. Nothing is created (a probe file is created and removed)."""
    targets = [("--out-dir", out_dir), ("--out-std-dir", out_std_dir)]
    if vis is not None:
        targets.append(("--vis", vis or f"{Path(out_dir).resolve()}_vis"))
    for flag, value in targets:
        if value is not None and any(same_file(value, p) for p in inputs):
            raise InputError(f"{flag}: {value} is {source}; refusing to write there")
        inside = next((p for p in inputs if value is not None and is_inside(value, p)), None)
        if inside is not None:
            raise InputError(f"{flag}: {value} is inside {source} ({inside}); refusing to write among the inputs, "
                             f"choose a folder outside it")
    resolved = [os.path.realpath(v) for _, v in targets if v is not None]
    if len(set(resolved)) != len(resolved):
        raise InputError("--out-dir, --out-std-dir and --vis: expected different folders")
    for flag, value in targets:
        if value is not None:
            check_output_folder(value, flag)
            with flagged(flag, value, "write"):
                check_not_locked(value, flag)  # another run writes there: refused now, not after the checks
    return targets


def check_output_folder(path: str | Path, flag: str) -> None:
    """An output folder to create or write into: not a file, and the folder (or, for one to be created, the
    nearest existing folder above it) takes new files. Nothing is created (a probe file is created and removed);
    errors name ``flag`` (a name too long, a path through a file ...)."""
    with flagged(flag, path, "write"):
        folder = Path(path)
        if folder.exists() and not folder.is_dir():
            raise InputError(f"{flag}: expected a folder, got a file: {folder}")
        # the folder, or the nearest one above it that exists (the run creates the rest), must take new files
        existing = next((p for p in (folder, *folder.absolute().parents) if p.exists()), None)
        if existing is not None and not existing.is_dir():
            raise InputError(f"{flag}: expected a folder, got a path under the file {existing}: {folder}")
        if existing is not None:
            check_writable_dir(existing, flag)


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


def is_inside(path: str | Path, folder: str | Path) -> bool:
    """Is ``path`` (existing or not) strictly inside ``folder``, links resolved?"""
    path, folder = Path(os.path.realpath(path)), Path(os.path.realpath(folder))
    return folder in path.parents


def _write_new(path: Path, data: bytes) -> None:
    """Write ``data`` to the new file ``path`` (created exclusively, mode 0o666 less the umask): the one place
    where the commands' output bytes reach the disk."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    with os.fdopen(fd, "wb") as handle:
        handle.write(data)


def _stage(flag: str, path: Path, data: bytes) -> Path:
    """``data`` written to a new temporary file beside ``path``; returns it. On failure it is removed and the
    error names ``flag`` and ``path`` (:func:`~crfdepth.io.file_errors.cannot_write`). The temporary name does
    not repeat the output's, so that an output name the file system takes never fails for its length."""
    temporary = path.parent / f".crfdepth-{secrets.token_hex(6)}.tmp"
    try:
        _write_new(temporary, data)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise cannot_write(exc, flag, path) from None
        raise
    return temporary


def write_files(files: list[tuple[str, Path, bytes]]) -> None:
    """Write each ``(flag, path, data)`` of ``files`` as one whole: every file to a temporary file beside it,
    then each renamed over its ``path`` (``os.replace``, atomic on one file system). When a write or a rename
    fails, or Ctrl-C comes, the temporary files are removed and so are the files already renamed, and the
    error names the flag and the path (:class:`~crfdepth.io.file_errors.FileError`): none of the files is
    left from this call, partial or whole (a file of the same name from before is then gone too)."""
    staged: list[tuple[str, Path, Path]] = []
    placed: list[Path] = []
    try:
        for flag, path, data in files:
            staged.append((flag, Path(path), _stage(flag, Path(path), data)))
        for flag, path, temporary in staged:
            try:
                os.replace(temporary, path)
            except OSError as exc:
                raise cannot_write(exc, flag, path) from None
            placed.append(path)
    except BaseException:
        for path in [temporary for _, _, temporary in staged] + placed:
            with contextlib.suppress(OSError):
                path.unlink(missing_ok=True)
        raise


def _png(image: np.ndarray, flag: str, path: Path) -> bytes:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - cv2 encodes any uint8 / uint16 array of 1 or 3 channels
        raise InputError(f"{flag}: could not encode an array of shape {image.shape} {image.dtype} as PNG for {path}")
    return encoded.tobytes()


def _rgb_png(rgb: np.ndarray, flag: str, path: Path) -> bytes:
    return _png(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), flag, path)


def _depth_png(depth: np.ndarray, flag: str, path: Path) -> bytes:
    """The KITTI depth PNG of ``depth`` (metres, finite, >= 0), as :func:`crfdepth.io.kitti.write_depth_png`
    encodes it: uint16 ``round(depth * 256)``, clipped to the largest code."""
    return _png(depth_png_codes(depth, path), flag, path)


def write_depth_png(path: Path, depth: np.ndarray, flag: str) -> None:
    """Write ``depth`` (metres, finite, >= 0) as a KITTI depth PNG, atomically; errors name ``flag``."""
    write_files([(flag, path, _depth_png(depth, flag, path))])


def write_rgb_png(path: Path, rgb: np.ndarray, flag: str) -> None:
    """Write an (H, W, 3) uint8 RGB picture as PNG, atomically (temporary file + rename); errors name ``flag``."""
    write_files([(flag, path, _rgb_png(rgb, flag, path))])


def _pictures(folder: Path, stem: str, depth: np.ndarray, std: np.ndarray | None,
              vis_range: tuple[float, float] | None, flag: str) -> list[tuple[str, Path, bytes]]:
    """The encoded ``<stem>_vis_depth.png`` (and ``<stem>_vis_std.png``) of :func:`write_pictures`."""
    pictures = [(folder / f"{stem}_vis_depth.png", depth_picture(depth, vis_range=vis_range))]
    if std is not None:
        pictures.append((folder / f"{stem}_vis_std.png", std_picture(std)))
    return [(flag, path, _rgb_png(picture, flag, path)) for path, picture in pictures]


def write_pictures(folder: Path, stem: str, depth: np.ndarray, std: np.ndarray | None,
                   vis_range: tuple[float, float] | None, flag: str = "--vis") -> list[Path]:
    """``<stem>_vis_depth.png`` and ``<stem>_vis_std.png`` with colour bars in metres, written together
    (:func:`write_files`); errors name ``flag``.

    ``vis_range`` fixes the depth colour scale (metres) for every frame of a sequence; the commands check it
    when the arguments are read (``crfdepth.cli.arguments.VisRange``).
    """
    files = _pictures(folder, stem, depth, std, vis_range, flag)
    write_files(files)
    return [path for _, path, _ in files]


def write_frame(depth: np.ndarray, std: np.ndarray | None, out: Path, out_std: Path | None, vis_dir: Path | None,
                stem: str, vis_range, flags: tuple[str, str, str] = ("--out", "--out-std", "--vis")) -> list[Path]:
    """A frame's depth PNG (and std PNG, and pictures into ``vis_dir``), written together (:func:`write_files`:
    all of them or none); returns the paths. ``flags`` name the outputs in errors: the depth's, the std's and the
    pictures' (one frame: ``--out``, ``--out-std``, ``--vis``; a folder or bag: ``--out-dir``, ``--out-std-dir``,
    ``--vis``). PNG values are clipped below at 1/256 m so that no pixel reads as "no value"."""
    if not np.all(np.isfinite(depth)):
        raise InputError(f"{flags[0]} {out}: the model returned {int(np.sum(~np.isfinite(depth)))} non-finite "
                         f"depth value(s); nothing written")
    files = [(flags[0], out, _depth_png(np.maximum(depth, _MIN_DEPTH), flags[0], out))]
    if out_std is not None:
        std_codes = np.maximum(np.nan_to_num(std, nan=_MIN_DEPTH), _MIN_DEPTH)
        files.append((flags[1], out_std, _depth_png(std_codes, flags[1], out_std)))
    if vis_dir is not None:
        files += _pictures(vis_dir, stem, depth, std, vis_range, flags[2])
    write_files(files)
    return [path for _, path, _ in files]


@contextlib.contextmanager
def rerun_recording(rerun: str | None) -> Iterator[Recorder | None]:
    """``--rerun FILE.rrd`` (``rerun``) checked (a ``.rrd`` name in a folder that takes new files) and rerun-sdk
    imported, before any computation, then a :class:`~crfdepth.pictures.rerun_recording.Recorder` for the ``with``
    block, written atomically when the block ends (none on an error); ``""`` (a bare ``--rerun``) streams to a
    viewer; None yields None. Errors are one line naming ``--rerun``."""
    if rerun is None:
        yield None
        return
    path = None
    if rerun:
        with flagged("--rerun", rerun, "write"):  # a name too long, a path through a file ...
            path = check_output_file(rerun, "--rerun", suffix=".rrd")
    import_rerun("--rerun")
    with open_recording(path, name="--rerun") as stream:  # not flagged: the block's own errors are the command's
        yield Recorder(stream)
