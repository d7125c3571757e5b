"""What the image decoders' C libraries print on stderr, kept off a command's output (docs/design.md section 11).

libpng writes its warnings with ``fprintf(stderr, ...)`` (``libpng warning: iCCP: known incorrect
sRGB profile``), libjpeg its own (``Corrupt JPEG data: 3 extraneous bytes``) and OpenCV logs
``[ WARN:0@0.1] global grfmt_png.cpp:793 ... PNG input buffer is incomplete``: C code writing to file
descriptor 2, which neither ``sys.stderr`` nor ``warnings`` sees. A command line's stderr must start
with its one error line, and a file that decodes fine despite a warning is no news for the user; the
reader's own message says what is wrong with a file that does not decode.

:func:`quiet_decoders` captures file descriptor 2 around a decode and, on leaving, writes back what
is not decoder noise (:data:`NOISE`: a Python warning or log line printed meanwhile still shows).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Iterator

__all__ = ["NOISE", "quiet_decoders"]

# Lines of the decoders' C libraries: libpng, libjpeg(-turbo), libtiff, libwebp and OpenCV's own log.
NOISE = re.compile(rb"^(libpng (warning|error)|\[ ?(WARN|ERROR|INFO|DEBUG|VERBOSE)\s*:|Corrupt JPEG data|"
                   rb"Premature end of JPEG file|Invalid SOS parameters|Unsupported marker type|JPEG datastream|"
                   rb"Bogus marker|TIFF\w*: )")


def _flush_stderr() -> None:
    with contextlib.suppress(Exception):  # a closed or replaced stream: nothing of ours is pending there
        sys.stderr.flush()


@contextlib.contextmanager
def quiet_decoders() -> Iterator[None]:
    """Within the block, file descriptor 2 goes to a temporary file; on leaving, its lines that are not
    decoder noise (:data:`NOISE`) are written to stderr, in order. Where file descriptor 2 is not open or no
    temporary file can be made (a full disk), the block runs as it is."""
    _flush_stderr()
    try:
        capture = tempfile.TemporaryFile()
    except OSError:
        yield
        return
    with capture:
        try:
            saved = os.dup(2)
        except OSError:
            yield
            return
        try:
            os.dup2(capture.fileno(), 2)
            yield
        finally:  # also when the block raises: a Python warning printed before the error still shows
            _flush_stderr()
            os.dup2(saved, 2)
            os.close(saved)
            capture.seek(0)
            kept = [line for line in capture.read().splitlines(keepends=True) if not NOISE.match(line)]
            if kept:
                with contextlib.suppress(OSError):
                    os.write(2, b"".join(kept))
