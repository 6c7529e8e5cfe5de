"""``python -m uavlae.experiments.archive RUNS_DIR OUT.tar.xz``: a runs directory's records in one file.

What the report reads (configs, metadata, final metrics, scalar logs, evaluation records, the
evaluation sets, Hydra's multirun records) goes in as it is. Left out: wandb files, pictures
and the report, which are rebuilt. A finished training run's checkpoint goes in without its
replay buffer and its collector's state (both set to None: under a megabyte instead of 1.5 GB);
the learner, counters and config left are all that ``uavlae.evaluate`` reads, so the scenario
sweeps can still evaluate it after

    mkdir -p runs && tar xJf OUT.tar.xz -C runs

An unfinished run's checkpoint is left out (resuming it needs the buffer): that run starts
again. The archive is written atomically.
"""

from __future__ import annotations

import argparse
import io
import tarfile
from pathlib import Path

import torch

from uavlae.files import atomic_write

SKIP_DIRS = {"wandb", "report"}
SKIP_SUFFIXES = {".png", ".pdf"}


def _lean_checkpoint(path: Path) -> bytes:
    state = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
    state["replay_buffer"] = state["collector"] = None
    buf = io.BytesIO()
    torch.save(state, buf)
    return buf.getvalue()


def archive(runs_dir: Path, out: Path) -> list[str]:
    """Write ``out`` (a .tar.xz whose top folder is ``runs_dir``'s name); returns its members."""
    runs_dir = runs_dir.resolve()
    names: list[str] = []

    def write(fh) -> None:
        with tarfile.open(fileobj=fh, mode="w:xz") as tar:
            for f in sorted(runs_dir.rglob("*")):
                rel = f.relative_to(runs_dir)
                if not f.is_file() or SKIP_DIRS & set(rel.parts) or f.suffix in SKIP_SUFFIXES:
                    continue
                arc = str(Path(runs_dir.name) / rel)
                if "checkpoints" in rel.parts:
                    run = f.parent.parent
                    if f.name != "last.pt" or not (run / "final_metrics.json").is_file():
                        continue
                    data = _lean_checkpoint(f)
                    info = tarfile.TarInfo(arc)
                    info.size = len(data)
                    tar.addfile(info, io.BytesIO(data))
                else:
                    tar.add(f, arcname=arc, recursive=False)
                names.append(arc)

    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, write)
    return names


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs_dir", type=Path)
    p.add_argument("out", type=Path)
    a = p.parse_args(argv)
    if not a.runs_dir.is_dir():
        p.error(f"{a.runs_dir} is not a directory")
    names = archive(a.runs_dir, a.out)
    print(f"{len(names)} files -> {a.out} ({a.out.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
