"""Progress of a run over many frames, shown by the caller: a run asks ``progress(desc, total)`` (the caller's
factory, e.g. the command line's progress bar) for an object with ``update(n)`` (``n`` more frames done) and
``close()``; without a factory, or with ``quiet``, nothing is shown."""

from __future__ import annotations

__all__ = ["bar"]


class _NoBar:
    """The progress of a run that shows none."""

    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def bar(run, desc: str, total: int):
    """The progress of ``total`` frames (``desc``: ``check``, ``complete``, ``evaluate``) of ``run``, whose fields
    ``progress`` (the factory, or None) and ``quiet`` say whether and how it is shown."""
    if run.progress is None or run.quiet:
        return _NoBar()
    return run.progress(desc, total)
