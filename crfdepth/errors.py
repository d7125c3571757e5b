"""The one exception type crfdepth raises for bad input, and what counts as bad input."""


class InputError(ValueError):
    """Bad input at a public boundary of crfdepth.

    The message names the argument, what was expected and what was received, for
    instance ``edge_weight: expected 1-D tensor of length 120 (one per edge), got shape
    (119,)``. Subclasses ``ValueError`` so callers that already catch that keep working.
    """


class ConvergenceError(RuntimeError):
    """An iterative solve stopped before reaching its tolerance (when asked to raise)."""


class ConvergenceWarning(UserWarning):
    """An iterative solve stopped before reaching its tolerance."""


BAD_INPUT = (InputError, FileNotFoundError, PermissionError, IsADirectoryError)
"""Bad input: what a run over many frames tells as a bad frame (``--skip-bad`` leaves it out, ``crfdepth targets``
tells it with how far the run got) and ``crfdepth.cli.main`` as one line with exit status 2. Not
:class:`~crfdepth.io.file_errors.FileError` (an output that cannot be written): that stops every run."""
