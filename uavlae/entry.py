"""How a command ends when it cannot do what it was asked: one message, not a traceback.

:func:`command` runs a ``@hydra.main`` function (``uavlae.train``, ``uavlae.evaluate``,
``uavlae.export``) as a command line. An error the user can fix (:data:`USER_ERRORS`: a setting
out of range or against a rule, a file that is missing or unusable, an LLM endpoint that cannot
answer, a run folder another process owns) and Hydra's own (an unknown key, an override it cannot
parse) print ``error: <message>`` on stderr, the message's own lines for several fields, and the
command exits with status 2. Anything else is a bug and keeps its traceback. ``UAVLAE_DEBUG=1``
(or Hydra's ``HYDRA_FULL_ERROR=1``) shows the traceback of a user error too.

Inside a training job, :func:`recorded` decides what a failed command leaves behind: a folder
that Hydra made for the job and that holds nothing of the run's own (its ``.hydra/``, its log,
the lock) is removed, so a refused command leaves no folder; a run folder that holds a
run gets ``error.txt``, the message (or, for a bug, the traceback), beside the run it ended.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

from uavlae.errors import UserError
from uavlae.lifecycle import RunFolderBusy

__all__ = ["ERROR_FILE", "USER_ERRORS", "command", "debug_asked", "recorded", "refused_in_job", "user_message"]

ERROR_FILE = "error.txt"
# when this process started its command: a Hydra folder older than that was not made by it
_STARTED = time.time()


def _user_errors() -> tuple[type[BaseException], ...]:
    from uavlae.llm.schema import CacheMissError, EndpointError
    from uavlae.llm.server import ServerStartError

    return (UserError, FileNotFoundError, RunFolderBusy, EndpointError, CacheMissError, ServerStartError)


USER_ERRORS = _user_errors()


def debug_asked() -> bool:
    """``UAVLAE_DEBUG`` or ``HYDRA_FULL_ERROR`` set to a true value: tracebacks for every error."""
    return any(os.environ.get(v, "").strip().lower() in ("1", "true", "yes", "on")
               for v in ("UAVLAE_DEBUG", "HYDRA_FULL_ERROR"))


def user_message(err: BaseException) -> str | None:
    """The message of a user error (Hydra's with its cause), or None for anything else (a bug)."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(err, HydraException):
        cause = err.__cause__
        extra = f"\n{cause}" if isinstance(cause, OmegaConfBaseException) and str(cause) not in str(err) else ""
        return f"{err}{extra}".strip()
    if isinstance(err, FileNotFoundError) and err.strerror and err.filename:
        return f"{err.strerror}: {err.filename}"  # the system's, without its "[Errno 2]"
    if isinstance(err, USER_ERRORS):
        return str(err).strip()
    return None


def _refuse(message: str) -> NoReturn:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


_asked: dict[str, bool] = {}  # what the user asked before command() set HYDRA_FULL_ERROR for Hydra


@contextlib.contextmanager
def refused_in_job() -> Iterator[None]:
    """Inside a Hydra job: a user error ends the command here, with its one message (raised on,
    Hydra would print ``Error executing job ...`` above it). A sweep's job raises it on, for its
    launcher to report as it reports any failed job."""
    try:
        yield
    except Exception as err:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        message = user_message(err)
        debug = _asked.get("debug", debug_asked())
        if message is None or debug or HydraConfig.get().mode == RunMode.MULTIRUN:
            raise
        _refuse(message)


def command(main: Callable[[], Any]) -> Any:
    """Run ``main`` (a ``@hydra.main`` function, which reads ``sys.argv``) as a command (module doc)."""
    debug = _asked["debug"] = debug_asked()
    previous = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises what it caught instead of printing it with its hint
    try:
        return main()
    except Exception as err:  # noqa: BLE001  (sorted below: a user error is printed, a bug raised)
        message = user_message(err)
        if message is None or debug:
            raise
        _refuse(message)
    finally:
        if previous is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = previous


def _hydra_only(folder: Path, job_log: str) -> bool:
    """``folder`` holds nothing but what Hydra and the lock wrote for this process's job."""
    names = {p.name for p in folder.iterdir()}
    if not names <= {".hydra", job_log, ".lock"}:
        return False
    made = folder / ".hydra" / "overrides.yaml"
    return not made.exists() or made.stat().st_mtime >= _STARTED - 1.0


def _remove(folder: Path, job_log: str) -> None:
    import shutil

    shutil.rmtree(folder / ".hydra", ignore_errors=True)
    for name in (job_log, ".lock"):
        (folder / name).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        folder.rmdir()  # only when empty now: never a folder that held anything else


@contextlib.contextmanager
def recorded(hydra_dir: Path | None, run_dir: Callable[[], Path | None], job_log: str) -> Iterator[None]:
    """A training job's failure, as the module doc says: ``hydra_dir`` is the folder Hydra made
    for the job (None: none), ``run_dir()`` the run's own folder (None: unknown), ``job_log`` the
    name of Hydra's log file in it."""
    try:
        yield
    except Exception as err:
        message = user_message(err)
        target = _safe(run_dir)
        if target is not None and (target / "config.json").is_file():
            text = message if message is not None else "".join(traceback.format_exception(err))
            with contextlib.suppress(OSError):
                (target / ERROR_FILE).write_text(text + "\n")
        for folder in {p for p in (hydra_dir, target) if p is not None}:
            if folder.is_dir() and _hydra_only(folder, job_log):
                _remove(folder, job_log)
        raise


def _safe(run_dir: Callable[[], Path | None]) -> Path | None:
    try:
        return run_dir()
    except Exception:  # noqa: BLE001  (a resume= that names nothing: there is no run folder)
        return None
