"""The RIB's sqlite file: its schema and version, the one shared connection and its transactions.

`RibStore` owns the file (open, check, create, close) and how statements run on it: every
write in a short transaction (`_tx`, joined by nested calls), reads under the same lock.
`registry.rib.Rib` adds the routing tables' operations on top.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

from common.errors import UserError

SCHEMA_VERSION = 2
BUSY_TIMEOUT_MS = 2_000
MEMORY = ":memory:"

_Store = TypeVar("_Store", bound="RibStore")

_SCHEMA = """
CREATE TABLE deployments (
    id           TEXT PRIMARY KEY,
    service      TEXT NOT NULL,
    model_digest TEXT NOT NULL,
    capacity     INTEGER NOT NULL,
    load         INTEGER NOT NULL,
    version      TEXT NOT NULL,
    last_seen    REAL NOT NULL,
    alive        INTEGER NOT NULL,
    draining     INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE deployment_states (
    deployment TEXT NOT NULL,
    robot      TEXT NOT NULL,
    state      TEXT NOT NULL CHECK (state IN ('standby', 'service', 'draining')),
    epoch      INTEGER NOT NULL,
    PRIMARY KEY (deployment, robot)
);
CREATE TABLE robots (
    id        TEXT PRIMARY KEY,
    service   TEXT NOT NULL,
    alive     INTEGER NOT NULL,
    last_seen REAL NOT NULL
);
CREATE TABLE routes (
    robot         TEXT PRIMARY KEY,
    deployment    TEXT,
    epoch         INTEGER NOT NULL,
    since         REAL NOT NULL,
    issued_epoch  INTEGER NOT NULL,
    pool          TEXT NOT NULL DEFAULT '[]'
);
CREATE TABLE profiles (
    robot      TEXT NOT NULL,
    deployment TEXT NOT NULL,
    source     TEXT NOT NULL CHECK (source IN ('telemetry', 'probe')),
    samples    TEXT NOT NULL,
    updated_at REAL NOT NULL,
    PRIMARY KEY (robot, deployment, source)
);
CREATE TABLE events (
    seq        INTEGER PRIMARY KEY AUTOINCREMENT,
    ts         REAL NOT NULL,
    kind       TEXT NOT NULL,
    robot      TEXT,
    deployment TEXT,
    epoch      INTEGER,
    reason     TEXT NOT NULL
);
CREATE INDEX events_robot ON events (robot, seq);
"""
# Statements that bring a file of the version before to the next one (a file is migrated in one
# transaction when it is opened). 1 -> 2: round-robin pools (`routes.pool`, a JSON list).
_MIGRATIONS: dict[int, tuple[str, ...]] = {
    1: ("ALTER TABLE routes ADD COLUMN pool TEXT NOT NULL DEFAULT '[]'",),
}
_TABLES = frozenset({"deployments", "deployment_states", "robots", "routes", "profiles", "events"})


class RibStore:
    """One sqlite file (or `":memory:"` for tests) holding the RIB's tables, behind one lock."""

    def __init__(self, path: str | Path, *, clock: Callable[[], float] = time.time) -> None:
        self.path = str(path)
        self._clock = clock
        self._lock = threading.RLock()
        if self.path != MEMORY:
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        try:
            # Autocommit mode: transactions are opened explicitly in `_tx`.
            self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as exc:
            raise UserError(f"cannot open the RIB at {self.path}: {exc}") from None
        try:
            self._open()
        except sqlite3.DatabaseError as exc:
            self._conn.close()
            raise UserError(f"{self.path} is not an elasticfog RIB (sqlite: {exc})") from None
        except UserError:
            self._conn.close()
            raise

    # -- lifecycle ---------------------------------------------------------------------------
    def _open(self) -> None:
        conn = self._conn
        conn.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
        version = int(conn.execute("PRAGMA user_version").fetchone()[0])
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if version == 0:
            if tables:
                raise UserError(
                    f"{self.path} is a sqlite file with other tables ({', '.join(sorted(tables))}),"
                    " not an elasticfog RIB"
                )
            # Statement by statement: executescript would commit halfway through the transaction.
            with self._tx():
                for statement in _SCHEMA.split(";"):
                    if statement.strip():
                        conn.execute(statement)
                conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        elif version in _MIGRATIONS:
            if missing := sorted(_TABLES - tables):
                raise UserError(f"{self.path}: RIB tables are missing ({', '.join(missing)})")
            with self._tx():
                for old in range(version, SCHEMA_VERSION):
                    for statement in _MIGRATIONS[old]:
                        conn.execute(statement)
                conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        elif version != SCHEMA_VERSION:
            raise UserError(
                f"{self.path}: RIB schema version {version} is not supported (this elasticfog reads"
                f" version {SCHEMA_VERSION}); move the file away to start a fresh RIB"
            )
        elif missing := sorted(_TABLES - tables):
            raise UserError(f"{self.path}: RIB tables are missing ({', '.join(missing)})")
        # WAL: the CLI's read-only views never wait for a scheduler write. NORMAL sync is durable
        # across a process crash, which is the failure the RIB has to survive.
        conn.execute("PRAGMA journal_mode = WAL")
        conn.execute("PRAGMA synchronous = NORMAL")

    def close(self) -> None:
        """Close the file; the object is unusable afterwards."""
        with self._lock:
            self._conn.close()

    def __enter__(self: _Store) -> _Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            conn = self._conn
            # Nested use joins the caller's transaction instead of opening a second one.
            own = not conn.in_transaction
            if own:
                conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                if own:
                    conn.execute("ROLLBACK")
                raise
            else:
                if own:
                    conn.execute("COMMIT")

    def _query(self, sql: str, params: Sequence[Any] = ()) -> list[sqlite3.Row]:
        with self._lock:
            cur = self._conn.cursor()
            cur.row_factory = sqlite3.Row
            return list(cur.execute(sql, params))
