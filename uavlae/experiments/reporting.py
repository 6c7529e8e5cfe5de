"""What every report writer of the study shares, written once: reading a run's records (a JSON
file, the rows of a CSV file, a scalar the run logged), writing what a report is made of (text,
a CSV table, a Markdown table, a figure as PNG and PDF) and the one way an interval is written.

A committed report regenerates byte for byte from its records (tests/test_experiments.py), so
everything here writes the same bytes for the same input: text is UTF-8, a file is replaced
atomically, a PDF carries no creation date.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from uavlae.files import atomic_write


# ---------------------------------------------------------------------------- reading


def read_json(path: Path) -> Any:
    """The JSON in ``path``; a file that cannot be read or parsed is a ``ValueError`` naming it."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{Path(path).name}: {err}") from None


def read_rows(path: Path) -> list[dict[str, str]]:
    """The rows of the CSV file ``path`` (its header names the columns); none when it is missing."""
    path = Path(path)
    if not path.is_file():
        return []
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def cell_true(value: Any) -> bool:
    """Whether a CSV cell holds a true flag: the records write bools as ``True``/``False``, and
    tables built elsewhere (pandas, a spreadsheet) as ``true``, ``1`` or ``1.0``."""
    return str(value).strip().lower() in ("true", "1", "1.0")


def read_scalar(run_dir: Path, name: str) -> list[tuple[float, float]]:
    """``(step, value)`` of the scalar ``name`` a run logged (``logs/scalars/<name>.csv``: torchrl's
    CSV logger, ``step,value`` lines without a header); none when the run never logged it. A line
    that is not two numbers is passed over."""
    f = Path(run_dir) / "logs" / "scalars" / f"{name}.csv"
    if not f.is_file():
        return []
    out = []
    for line in f.read_text().splitlines():
        parts = line.split(",")
        if len(parts) >= 2:
            try:
                out.append((float(parts[0]), float(parts[1])))
            except ValueError:
                continue
    return out


# ---------------------------------------------------------------------------- writing


def write_text(path: Path, text: str) -> None:
    """``text`` into ``path`` as UTF-8, atomically (a reader never sees half a report)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))


def write_csv(path: Path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None) -> None:
    """``rows`` as a CSV table. ``columns``: exactly these, in this order (a row's other keys are
    left out, a missing one is empty), so a reader finds them even with no row; None: the rows'
    keys in the order they first appear (``empty`` as the one column of a table without rows)."""
    keys = list(columns) if columns is not None else (list(dict.fromkeys(k for r in rows for k in r)) or ["empty"])
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    write_text(path, buf.getvalue())


def markdown_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str], empty: str | None = None) -> list[str]:
    """The lines of a Markdown table: ``columns`` as the header, each row's cells by column name
    (a missing one is empty). ``empty``: the one line written instead when there is no row."""
    if not rows and empty is not None:
        return [empty]
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(r.get(c, "")) for c in columns) + " |" for r in rows]
    return lines


def fmt_interval(point: float, lo: float, hi: float, digits: int = 3) -> str:
    """``point [lo, hi]``; the point alone where there is no interval (``lo`` NaN: one seed),
    ``n/a`` where there is no point."""
    if not math.isfinite(point):
        return "n/a"
    if math.isnan(lo):
        return f"{point:.{digits}f}"
    return f"{point:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def save_figure(fig: Any, out: Path, stem: str, *, note: str = "", dpi: float | None = None,
                tight: bool = False) -> list[str]:
    """``fig`` as ``<stem>.png`` and ``<stem>.pdf`` in ``out``, then closed; the names written.
    ``note``: a line in italics below the axes' labels; ``dpi`` (None: the figure's own) and
    ``tight`` (the bounding box cut to what is drawn) as matplotlib's ``savefig`` takes them.
    The PDF carries no creation date, so a figure's bytes change only when its content does."""
    import matplotlib.pyplot as plt  # deferred: pyplot starts a backend, and only a figure needs one

    if note:
        fig.text(0.01, -0.02, note, fontsize=7, ha="left", va="top", style="italic")
    names = []
    for ext in ("png", "pdf"):
        path = Path(out) / f"{stem}.{ext}"
        fig.savefig(path, dpi=dpi, bbox_inches="tight" if tight else None,
                    metadata={"CreationDate": None} if ext == "pdf" else None)
        names.append(path.name)
    plt.close(fig)
    return names
