"""What a run over many frames does with its bad frames: refuses them all, listed, or (``--skip-bad``)
leaves them out and lists them in ``<out-dir>/skipped.csv`` (folder and bag modes); and what counts as a bad
frame, :data:`BAD_INPUT`."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from crfdepth.errors import InputError
from crfdepth.runs.outputs import write_files

__all__ = ["FAILED_CSV", "LISTED_BAD", "SKIPPED_CSV", "skipped_frames", "write_failed", "write_skipped"]

SKIPPED_CSV = "skipped.csv"  # --skip-bad: the frames left out and why (folder and bag modes)
FAILED_CSV = "failed.csv"  # folder mode: the frames that passed the checks but failed when completed
# How many bad frames the error of a run without --skip-bad lists (the first line names the first one).
LISTED_BAD = 20


def write_skipped(out_dir: Path, skipped: list[tuple[str, str]]) -> Path | None:
    """``<out-dir>/skipped.csv`` (columns ``frame``, ``reason``) of the frames ``--skip-bad`` left out,
    written atomically; with none, a ``skipped.csv`` of an earlier run is removed, so that the folder
    describes this run. Returns the file written, or None."""
    return _write_frame_list(out_dir / SKIPPED_CSV, skipped)


def write_failed(out_dir: Path, failed: list[tuple[str, str]]) -> Path | None:
    """``<out-dir>/failed.csv`` (columns ``frame``, ``reason``) of the frames that passed the checks but failed
    when completed, as :func:`write_skipped` writes its list; ``--resume`` completes them once fixed."""
    return _write_frame_list(out_dir / FAILED_CSV, failed)


def _write_frame_list(path: Path, rows: list[tuple[str, str]]) -> Path | None:
    if not rows:
        path.unlink(missing_ok=True)
        return None
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(("frame", "reason"))
    writer.writerows(rows)
    write_files([("--out-dir", path, text.getvalue().encode())])
    return path


def skipped_frames(bad: list[tuple[int, type[BaseException], str]], total: int, what: str,
                   skip_bad: bool) -> dict[int, str]:
    """The frames a run over ``total`` frames leaves out, ``{index: message}``, after its check pass found
    ``bad`` ones (index, exception type, message naming the frame); ``what`` names the source
    (``--input-dir DIR``, ``--bag FILE``).

    Raises, so that nothing is written: without ``skip_bad``, the first bad frame's exception with the
    count on its first line and the further bad frames below it (up to ``LISTED_BAD`` in all); with it,
    an InputError when every frame is bad.
    """
    if bad and not skip_bad:
        _, error, first = bad[0]
        more = "" if len(bad) == 1 else ", listed below"
        lines = [f"{first} [{len(bad)} of {total} frame(s) of {what} bad{more}; nothing written; fix them, or give "
                 f"--skip-bad to complete the others]"]
        lines += [f"  {message}" for _, _, message in bad[1:LISTED_BAD]]
        if len(bad) > LISTED_BAD:
            lines.append(f"  ... and {len(bad) - LISTED_BAD} more")
        raise error("\n".join(lines))
    if bad and len(bad) == total:
        raise InputError(f"--skip-bad: all {total} {'paired ' if what.startswith('--bag') else ''}frame(s) of {what} "
                         f"are bad (the first: {bad[0][2]}); nothing written")
    return {index: message for index, _, message in bad}
