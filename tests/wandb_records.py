"""Read an offline wandb run (``offline-run-*/run-*.wandb``) back: its group, name, tags, job type,
last summary values, history rows and the tables it logged, as the dashboard will show them
after ``wandb sync``.

The file is a sequence of ``wandb.proto.wandb_internal_pb2.Record`` messages in the LevelDB log
format (a 7-byte header ``:W&B``, 0xBEE1, version 0; 32 KiB blocks of chunks with a 7-byte
header: CRC, length, type full/first/middle/last). wandb's own Python reader of this format left
the package when its core moved to Go; this one is the single place that knows the format, and
the tests that use it fail if wandb changes it.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

BLOCK, HEADER = 32768, 7
FULL, FIRST, MIDDLE, LAST = 1, 2, 3, 4


def _records(path: Path) -> list[bytes]:
    data = path.read_bytes()
    ident, magic, version = struct.unpack("<4sHB", data[:HEADER])
    assert (ident, magic, version) == (b":W&B", 0xBEE1, 0), f"{path}: not a wandb run file ({ident!r}, {magic:#x})"
    out, pending, pos = [], b"", HEADER
    while pos + HEADER <= len(data):
        left = BLOCK - pos % BLOCK
        if left < HEADER:  # a block's tail too short for a chunk header is padding
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + HEADER])
        pos += HEADER
        if kind == 0 and length == 0:
            break
        chunk, pos = data[pos:pos + length], pos + length
        if kind == FULL:
            out.append(chunk)
        elif kind == FIRST:
            pending = chunk
        elif kind == MIDDLE:
            pending += chunk
        elif kind == LAST:
            out.append(pending + chunk)
    return out


def _key(item: Any) -> str:
    return item.key or "/".join(item.nested_key)


def read_offline_run(run_dir: Path) -> dict[str, Any]:
    """``run_dir``: an ``offline-run-*`` folder. Returns ``group``, ``name``, ``tags``, ``job_type``,
    ``summary`` (key -> last value), ``history`` (one dict per logged row) and ``tables`` (key ->
    ``{"columns", "data"}`` read from the table files the run wrote)."""
    from wandb.proto import wandb_internal_pb2 as pb

    (file,) = Path(run_dir).glob("run-*.wandb")
    out: dict[str, Any] = {"summary": {}, "history": [], "tables": {}}
    for raw in _records(file):
        rec = pb.Record()
        rec.ParseFromString(raw)
        kind = rec.WhichOneof("record_type")
        if kind == "run":
            r = rec.run
            out.update(group=r.run_group, name=r.display_name, tags=list(r.tags), job_type=r.job_type, id=r.run_id)
        elif kind == "summary":
            out["summary"].update({_key(i): json.loads(i.value_json) for i in rec.summary.update})
        elif kind == "history":
            out["history"].append({_key(i): json.loads(i.value_json) for i in rec.history.item})
    for row in out["history"]:
        for key, value in row.items():
            if key.endswith("/_type") and value == "table-file":
                name = key[: -len("/_type")]
                table = json.loads((Path(run_dir) / "files" / row[f"{name}/path"]).read_text())
                out["tables"][name] = {"columns": table["columns"], "data": table["data"]}
    return out
