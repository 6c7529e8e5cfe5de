"""``python -m uavlae.experiments.records RUNS_DIR OUT_DIR``: what the report needs of a runs
directory, small enough to commit, and naming no folder of the machine that made it.

``uavlae.experiments.report OUT_DIR`` regenerates from these records the same tables, figures
and report as from ``RUNS_DIR`` itself: ``make experiments-results`` writes the records first and
the committed report from them, and a test regenerates every committed report from its records.
Kept, with the same paths as in ``RUNS_DIR``:

- a training run (``uavlae.train``): ``config.json``, ``meta.json`` (the commit, the package
  versions, the machine and the command that reruns it), ``final_metrics.json`` (the final
  metrics and the training wall clock), the curves the report draws and counts
  (:data:`CURVES` of ``logs/scalars/``), each evaluation's ``metrics.json`` (the evaluation
  curve) and the final evaluation's per-episode records (``episodes.csv``);
- an evaluation (``uavlae.evaluate``): ``evaluation.json`` and its ``episodes.csv``;
- a sweep's record of its command line (``.multirun/<sweep>/<time>/multirun.yaml``, cut to the
  job's name and overrides).

Left out: checkpoints, the replay buffers, wandb files, pictures, Hydra's per-job folders, logs
of text and every other scalar. A run made from these records cannot be resumed or evaluated
again (no checkpoint); the sweeps add seeds or settings beside them.

Paths inside the records are made relative: the runs directory's absolute path becomes the path
it is given by (relative to ``--base``, the working directory by default), and any path under
``--base`` becomes relative to it. An absolute path left after that is an error that names the
file and the key, so that no record carries the machine's folders.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import yaml

from uavlae.experiments.reporting import read_json
from uavlae.files import ABSOLUTE_PATH, train_eval_dir

METRICS = ("DCR", "CR", "SLR", "RVR", "ECR")
# The scalar curves the report reads: Fig. 3 (return against frames and against training
# episodes), the evaluation curve of a long run, and the advisor's calls and cache hits.
CURVES = ("episode/mean_return", "train/episodes", *(f"eval/{m}" for m in METRICS))
ADVISOR_CURVES = ("calls.csv", "cache_hits.csv")  # anywhere under logs/scalars/override/
# meta.json: what the report and a reader need; argv (the launcher's, with its absolute path) and
# the pid are the process's, not the run's
META_KEYS = ("git", "packages", "machine", "command", "overrides")


def _relative(value: Any, swaps: list[tuple[str, str]], where: str, found: list[str]) -> Any:
    """``value`` with every ``(absolute prefix, replacement)`` of ``swaps`` applied to its strings;
    the absolute paths left are appended to ``found`` as ``"where: path"``."""
    if isinstance(value, dict):
        return {k: _relative(v, swaps, f"{where}.{k}", found) for k, v in value.items()}
    if isinstance(value, list):
        return [_relative(v, swaps, f"{where}[{i}]", found) for i, v in enumerate(value)]
    if not isinstance(value, str):
        return value
    for prefix, replacement in swaps:
        # the prefix as a whole folder: "/a/b" in "/a/b/c" and "/a/b", not in "/a/bc"
        value = re.sub(re.escape(prefix) + r"(/|(?=$|[\s'\",)\]]))",
                       lambda m: (replacement + m.group(1)) if replacement else ("" if m.group(1) else "."), value)
    found += [f"{where}: {m}" for m in ABSOLUTE_PATH.findall(value)]
    return value


def _load(path: Path) -> Any:
    """The JSON of ``path``, or None where it does not parse (kept as text, for the report to list)."""
    try:
        return read_json(path)
    except ValueError:
        return None


class Writer:
    """Copies records from ``runs_dir`` into ``out``; ``base``: the folder relative paths start at."""

    def __init__(self, runs_dir: Path, out: Path, base: Path):
        self.runs_dir, self.out = runs_dir.resolve(), out
        base = base.resolve()
        try:
            shown = self.runs_dir.relative_to(base).as_posix()
        except ValueError:
            shown = self.runs_dir.name
        # the runs directory first (a longer prefix than the base it may lie in)
        self.swaps = [(str(self.runs_dir), shown), (str(base), "")]
        self.found: list[str] = []
        self.files: list[str] = []

    def copy(self, src: Path) -> None:
        dst = self.out / src.relative_to(self.runs_dir)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dst)
        self.files.append(str(src.relative_to(self.runs_dir)))

    def json(self, src: Path, data: Any | None = None) -> None:
        """A JSON record with its paths made relative; one that does not parse is kept as text
        (its paths made relative all the same), for the report to list as broken."""
        rel = src.relative_to(self.runs_dir)
        if data is None:
            data = _load(src)
        if data is None:
            text = _relative(src.read_text(), self.swaps, str(rel), self.found)
        else:
            text = json.dumps(_relative(data, self.swaps, str(rel), self.found), indent=1, default=str)
        dst = self.out / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_text(text)
        self.files.append(str(rel))

    def train_run(self, d: Path) -> None:
        self.json(d / "config.json")
        meta = _load(d / "meta.json")
        self.json(d / "meta.json", {k: meta[k] for k in META_KEYS if k in meta} if isinstance(meta, dict) else None)
        final_file = d / "final_metrics.json"
        final = _load(final_file) if final_file.is_file() else None
        if final_file.is_file():
            self.json(final_file, final)
        scalars = d / "logs" / "scalars"
        for name in CURVES:
            if (scalars / f"{name}.csv").is_file():
                self.copy(scalars / f"{name}.csv")
        if (scalars / "override").is_dir():
            for f in sorted((scalars / "override").rglob("*.csv")):
                if f.name in ADVISOR_CURVES:
                    self.copy(f)
        for f in sorted((d / "eval").glob("frames_*/metrics.json")):
            self.copy(f)
        if isinstance(final, dict):
            episodes = train_eval_dir(d, int(final.get("frames", 0))) / "episodes.csv"
            if episodes.is_file():
                self.copy(episodes)

    def eval_run(self, d: Path) -> None:
        rec = _load(d / "evaluation.json")
        if isinstance(rec, dict) and isinstance(rec.get("meta"), dict):
            rec["meta"] = {k: rec["meta"][k] for k in META_KEYS if k in rec["meta"]}
        self.json(d / "evaluation.json", rec)
        if (d / "episodes.csv").is_file():
            self.copy(d / "episodes.csv")

    def sweep_command(self, f: Path) -> None:
        hc = (yaml.safe_load(f.read_text()) or {}).get("hydra") or {}
        keep = {"hydra": {"job": {"name": (hc.get("job") or {}).get("name")},
                          "overrides": {"task": list((hc.get("overrides") or {}).get("task") or [])}}}
        rel = f.relative_to(self.runs_dir)
        clean = _relative(keep, self.swaps, str(rel), self.found)
        dst = self.out / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_text(yaml.safe_dump(clean, sort_keys=False))
        self.files.append(str(rel))


def write_records(runs_dir: Path, out: Path, base: Path | None = None) -> list[str]:
    """Write the records of ``runs_dir`` to ``out`` (replaced as a whole, only once every record
    is written and clean); returns the files written, relative to ``out``."""
    runs_dir = Path(runs_dir)
    if not runs_dir.is_dir():
        raise FileNotFoundError(f"{runs_dir} is not a directory")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        w = Writer(runs_dir, tmp, Path.cwd() if base is None else Path(base))
        seen: set[Path] = set()
        for marker, reader in (("evaluation.json", w.eval_run), ("config.json", w.train_run)):
            for f in sorted(w.runs_dir.rglob(marker)):
                d = f.parent
                rel = d.relative_to(w.runs_dir)
                if any(p.startswith(".") for p in rel.parts) or "report" in rel.parts[:1] or d in seen:
                    continue  # Hydra's folders, a report written into the runs directory
                if marker == "config.json" and not (d / "meta.json").is_file():
                    continue  # not a uavlae.train run
                seen.add(d)
                reader(d)
        for f in sorted(w.runs_dir.glob(".multirun/*/*/multirun.yaml")):
            w.sweep_command(f)
        if w.found:
            raise ValueError(f"{len(w.found)} absolute path(s) left in the records of {runs_dir} (give --base the "
                             "folder the runs were made from):\n  " + "\n  ".join(w.found[:20]))
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return w.files


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m uavlae.experiments.records", description=__doc__.split("\n\n")[0])
    p.add_argument("runs_dir", type=Path, help="a sweeps' experiment.root (e.g. runs/quick)")
    p.add_argument("out", type=Path, help="where the records go (e.g. results/quick/runs); replaced as a whole")
    p.add_argument("--base", type=Path, default=None,
                   help="the folder the runs were made from: paths under it become relative (default: here)")
    a = p.parse_args(argv)
    if not a.runs_dir.is_dir():
        p.error(f"{a.runs_dir} is not a directory")
    files = write_records(a.runs_dir, a.out, a.base)
    size = sum((a.out / f).stat().st_size for f in files)
    print(f"{len(files)} files, {size / 1e6:.1f} MB -> {a.out}")


if __name__ == "__main__":
    main()
