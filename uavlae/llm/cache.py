"""Persistent, content-addressed SQLite cache of validated answers.

Key: SHA-256 of the canonical JSON of (model, messages, sampling settings, output format).
Only validated answers are stored, so a replay reproduces the actions a run executed.
Several processes may share one file: WAL journal, a busy timeout, and INSERT OR IGNORE
(the first answer stored for a key wins). The connection is opened lazily per process and
never pickled.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

from .schema import Advice

SCHEMA_VERSION = 1


def cache_key(payload: dict[str, Any]) -> str:
    blob = json.dumps({"v": SCHEMA_VERSION, **payload}, sort_keys=True, separators=(",", ":"),
                      ensure_ascii=False)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


class AdviceCache:
    def __init__(self, path: str | os.PathLike, busy_timeout_s: float = 30.0):
        self.path = Path(os.path.expanduser(str(path)))
        self.busy_timeout_s = busy_timeout_s
        self._conn: sqlite3.Connection | None = None
        self._pid: int | None = None
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:
        return {"path": self.path, "busy_timeout_s": self.busy_timeout_s}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["path"], state["busy_timeout_s"])  # type: ignore[misc]

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None or self._pid != os.getpid():  # a forked child opens its own
            self.path.parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None,
                                   check_same_thread=False)
            conn.execute(f"PRAGMA busy_timeout={int(self.busy_timeout_s * 1000)}")
            try:
                self._set_up(conn)
            except BaseException:
                conn.close()
                raise
            self._conn, self._pid = conn, os.getpid()
        return self._conn

    def _set_up(self, conn: sqlite3.Connection) -> None:
        """WAL mode and the table. When several processes open a new file at once, switching it
        to WAL can fail at once with "database is locked" (SQLite does not always call the busy
        handler there), so this retries with backoff until ``busy_timeout_s``."""
        deadline, delay = time.monotonic() + self.busy_timeout_s, 0.002
        while True:
            try:
                conn.execute("PRAGMA journal_mode=WAL")
                conn.execute("PRAGMA synchronous=NORMAL")
                conn.execute(
                    "CREATE TABLE IF NOT EXISTS advice (key TEXT PRIMARY KEY, model TEXT NOT NULL, "
                    "vx REAL NOT NULL, vy REAL NOT NULL, confidence REAL NOT NULL, "
                    "reasoning TEXT NOT NULL, created REAL NOT NULL)"
                )
                return
            except sqlite3.OperationalError as e:
                if "locked" not in str(e) and "busy" not in str(e):
                    raise
                if time.monotonic() >= deadline:
                    raise sqlite3.OperationalError(
                        f"LLM cache {self.path}: still locked after {self.busy_timeout_s} s ({e})"
                    ) from e
                time.sleep(delay)
                delay = min(2 * delay, 0.1)

    def get(self, key: str) -> Advice | None:
        with self._lock:
            row = self._connection().execute(
                "SELECT vx, vy, confidence, reasoning FROM advice WHERE key = ?", (key,)
            ).fetchone()
        if row is None:
            return None
        return Advice(vx=row[0], vy=row[1], confidence=row[2], reasoning=row[3], attempts=0,
                      source="cache")

    def put(self, key: str, model: str, advice: Advice) -> None:
        with self._lock:
            self._connection().execute(
                "INSERT OR IGNORE INTO advice VALUES (?, ?, ?, ?, ?, ?, ?)",
                (key, model, advice.vx, advice.vy, advice.confidence, advice.reasoning, time.time()),
            )

    def __len__(self) -> int:
        with self._lock:
            return int(self._connection().execute("SELECT COUNT(*) FROM advice").fetchone()[0])

    def close(self) -> None:
        with self._lock:
            if self._conn is not None and self._pid == os.getpid():
                self._conn.close()
            self._conn = None
