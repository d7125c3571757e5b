"""``--strategy ddp`` on one machine without a launcher: crfdepth starts its ``--devices`` ranks itself.

The ranks are started by torch's own elastic launcher (:mod:`torch.distributed.launcher.api`, what
``torchrun --standalone --nproc-per-node N`` runs: a rendezvous on a free local port, no restarts), as
Lightning's ``ddp`` strategy starts its processes: the same command line runs in each rank
(``python -m crfdepth ...``), which then joins the group by the environment the launcher set
(:func:`crfdepth.runs.ranks.ranks_from_environment`) and does its share like a rank under torchrun.

Rank 0 writes to this terminal: the model line, the progress bar, the summary, or the one-line error
that every rank raises alike (bad input found by rank 0 is shared with the others). The other ranks'
output goes to log files, removed afterwards. The launching process returns the ranks' exit status:
0 when every rank succeeded, else that of the rank that failed first (2 for bad input, 130 for Ctrl-C).
The launcher stops the other ranks as soon as one ends with an error, so the ranks leave the group
together (:meth:`crfdepth.runs.ranks.Ranks.close`) and rank 0 prints the error they all raise as it leaves,
before any rank has ended. A failure of one rank alone (a bug) shows that rank's output (its traceback);
a rank killed before it could report (out of memory, a signal) is an error naming it.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import signal
import sys
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

from crfdepth.errors import InputError

__all__ = ["launch_ranks"]

# The launcher's own loggers: its INFO/WARNING/ERROR lines (the rendezvous, "failed (exitcode: 2)") repeat
# what the ranks report, in another form.
_LAUNCHER_LOGGERS = ("torch.distributed.elastic", "torch.distributed.launcher")
# The exit statuses of the errors that every rank raises alike (bad input: 2, Ctrl-C: 130; the command's main):
# rank 0 reports them itself, also when the launcher stopped it before it ended.
_REPORTED = (2, 130)


def launch_ranks(argv: list[str] | None, devices: int) -> int:
    """Run the ``crfdepth`` command ``argv`` (None: this process's, ``sys.argv[1:]``) as ``devices`` ranks on this
    machine; returns their exit status (module docstring)."""
    # imported here: only the process that starts ranks needs the launcher (0.1 s to import)
    from torch.distributed.elastic.multiprocessing import DefaultLogsSpecs, Std
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch

    argv = [str(a) for a in (argv if argv is not None else sys.argv[1:])]
    logs = Path(tempfile.mkdtemp(prefix="crfdepth-ranks-"))
    others = {rank: Std.ALL for rank in range(1, devices)}  # rank 0 on the terminal, the others in logs
    config = LaunchConfig(min_nodes=1, max_nodes=1, nproc_per_node=devices, run_id=uuid.uuid4().hex,
                          rdzv_backend="c10d", rdzv_endpoint="localhost:0", max_restarts=0,
                          logs_specs=DefaultLogsSpecs(log_dir=str(logs), redirects=others))
    try:
        with _launcher_quiet():
            elastic_launch(config, sys.executable)("-m", "crfdepth", *argv)
    except ChildFailedError as exc:
        return _exit_status(exc.failures, devices, logs)
    except SignalException as exc:
        raise KeyboardInterrupt(f"(--strategy ddp: the launcher got {exc.sigval.name} and stopped the "
                                f"{devices} ranks)") from None
    finally:
        shutil.rmtree(logs, ignore_errors=True)
    return 0


def _exit_status(failures: dict, count: int, logs: Path) -> int:
    """The exit status of ranks of which ``failures`` (global rank -> ``ProcessFailure``) failed, showing the
    first failure's output where rank 0 cannot have reported it."""
    main = failures.get(0)
    if main is not None and main.exitcode > 0:  # rank 0 ended by itself, its message on the terminal
        return main.exitcode
    ended = {rank: failure for rank, failure in failures.items() if failure.exitcode > 0}
    if not ended:  # killed, each: name the first not stopped by the launcher (which sends SIGTERM)
        rank = min(failures, key=lambda r: (failures[r].exitcode == -signal.SIGTERM, r))
        raise InputError(f"--strategy ddp: rank {rank + 1}/{count} ended without reporting "
                         f"({failures[rank].signal_name()}); what the other ranks wrote stays")
    first = ended[min(ended)]
    if first.exitcode in _REPORTED:  # raised on every rank alike, and rank 0 reports before the group ends
        return first.exitcode
    for log in logs.glob(f"*/attempt_0/{first.local_rank}/stderr.log"):  # a rank's own failure: a bug's traceback
        sys.stderr.write(log.read_text())
    return first.exitcode


@contextlib.contextmanager
def _launcher_quiet() -> Iterator[None]:
    """Within the block, the launcher's loggers are silent (the ranks report for themselves)."""
    loggers = [logging.getLogger(name) for name in _LAUNCHER_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)
