"""Files written atomically: a temporary file beside the target, flushed to disk, then renamed
over it, so that a reader (or a run interrupted half-way) never sees a half-written file. The
file gets the mode any file of this process gets (0666 less the umask), not the temporary
file's private 0600, so a shared experiment folder stays readable by whom the umask allows.
Also where a training run puts its evaluations, for the writer and its readers alike."""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

__all__ = ["ABSOLUTE_PATH", "atomic_write", "dump_json", "finite", "portable", "train_eval_dir"]


def _file_mode() -> int:
    """0666 less the process's umask (read without changing it where /proc tells it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: read it by setting it, and put it back at once
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[bytes]], Any], *, previous: str | os.PathLike[str] | None = None) -> Path:
    """Call ``write(fh)`` on a binary file that becomes ``path`` only once it is complete.
    ``previous``: an existing ``path`` is first renamed to it (a one-deep backup). The parent
    folders are created. Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fchmod(fh.fileno(), _file_mode())
            os.fsync(fh.fileno())
        if previous is not None and path.exists():
            os.replace(path, previous)  # from here until the next line only the backup exists
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)
    return path


def dump_json(path: str | os.PathLike[str], obj: Any, *, indent: int | None = 1, allow_nan: bool = True) -> Path:
    """``obj`` as strict JSON in ``path``, atomically (objects JSON does not know are written as
    ``str``). A NaN or an infinity, which JSON has no word for, is written as ``null`` (what no
    value means: a metric over no episode, a cost without a price); ``allow_nan=False`` makes it
    an error instead, for files whose numbers must all be finite."""
    text = json.dumps(finite(obj) if allow_nan else obj, indent=indent, allow_nan=False, default=str)
    return atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))


def finite(obj: Any) -> Any:
    """``obj`` with every NaN and infinity (in dicts, lists and tuples, at any depth) as None,
    so that ``json.dumps(finite(obj), allow_nan=False)`` is strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


# an absolute path: a "/" that starts a token (the text's start, or after a space, "=", ":", a
# quote or a bracket) and two or more folder names; "~/x/y", "<tmp>/x/y" and URLs are not one
ABSOLUTE_PATH = re.compile(r"(?<![^\s=:'\"(\[,`])/[\w.+-]+(?:/[\w.+-]*)+")


def portable(text: str, root: str | os.PathLike[str]) -> str:
    """``text`` (a command line, a path) as a committed record should name its paths: relative to
    ``root`` (the checkout that made it; ``../other`` for a sibling checkout), the temporary folder
    as ``<tmp>``, so that nothing names a folder of the machine that wrote it."""
    root, tmp = os.path.realpath(root), os.path.realpath(tempfile.gettempdir())

    def one(m: re.Match[str]) -> str:
        path = os.path.realpath(m.group(0))
        inside = path == root or path.startswith(root + os.sep)
        if not inside and (path == tmp or path.startswith(tmp + os.sep)):
            return "<tmp>" + path[len(tmp):]
        return os.path.relpath(path, root)

    return ABSOLUTE_PATH.sub(one, text)


def train_eval_dir(run_dir: str | os.PathLike[str], frames: int) -> Path:
    """The folder of uavlae.train's evaluation at ``frames`` (its final one at the run's frames;
    the controllers' and the LLM alone's at 0)."""
    return Path(run_dir) / "eval" / f"frames_{frames:09d}"


def _fsync_dir(d: Path) -> None:
    """Make the rename itself durable (where the platform allows opening a folder)."""
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:  # pragma: no cover
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)
