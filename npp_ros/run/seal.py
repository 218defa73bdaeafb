"""The run file's seal: one SHA-256 digest over everything the run stored, written in every write transaction.

Per-trajectory checksums detect damage to the data; they leave the metadata, the certificate and the episode
log open to an edit that the replay of the log cannot tell apart (epsilon changed in both the metadata and the
certificate). The seal covers every stored value a gate or a resumed run reads: each meta key (the run's
metadata and spec, its identity and its certificate), and each column of the trajectories, points and episodes
tables (and robot_episodes, a run on a robot's own episodes). So that a refusal can name what no longer matches,
the seal keeps one digest per part (``meta 'epsilon'``, ``episodes.v_lb``, ``points.s_0``) in its own table, and
``run``, the digest over all of them, is the one that stands for the whole file (a signature signs it).

A value is serialized canonically, by its SQLite type: NULL, an integer in decimal, a real as its 8 IEEE
bytes (little-endian), text and blobs length-prefixed; a column's values in primary-key order. The points
table grows by whole trajectories and is by far the largest, so each of its columns is a hash chain over
trajectories (chain = SHA-256(chain || SHA-256(column values of the next trajectory, by step))): a commit
hashes only the trajectories it added, and a check recomputes every chain from the start. The other tables
are small and hashed whole at every commit (an episode's policy return is written after its row).

A file without the seal table (from before seals) reads as unsealed; its next write seals it. Unsealed is not
proof of age (dropping the table is an edit too): the deployment gate refuses such a file unless allowed by name.
The seal is a checksum, not a proof of authorship: anyone with this code can recompute it after an edit. A
signature over its digest (npp_ros.deployment.signing) is the proof.
"""

from __future__ import annotations

import hashlib
import sqlite3
import struct
from collections.abc import Iterable, Mapping
from contextlib import closing, suppress
from dataclasses import dataclass
from pathlib import Path

SEAL_TABLE = "seal"
RUN_PART = "run"  # the digest over every other part: the whole file's
THROUGH_PART = "points:through"  # how many trajectories the points chains cover
TABLES = ("meta", "trajectories", "points", "episodes", "robot_episodes", "lipschitz_choices")
_ORDER = {
    "trajectories": "id", "episodes": "episode", "points": "trajectory, step", "robot_episodes": "id",
    "lipschitz_choices": "trajectories",
}  # fmt: skip
_EMPTY = hashlib.sha256(b"").hexdigest()


def encode(value: object) -> bytes:
    """One SQLite value, canonically: its type, then its content, so no two values share a serialization."""
    if value is None:
        return b"N"
    if isinstance(value, bool):  # never stored as such by SQLite, but a caller's True is 1
        value = int(value)
    if isinstance(value, int):
        text = str(value).encode()
        return b"I" + struct.pack("<I", len(text)) + text
    if isinstance(value, float):
        return b"R" + struct.pack("<d", value)
    if isinstance(value, str):
        data = value.encode()
        return b"T" + struct.pack("<Q", len(data)) + data
    if isinstance(value, bytes):
        return b"B" + struct.pack("<Q", len(value)) + value
    raise TypeError(f"no canonical form for a stored {type(value).__name__}")


def _digest(values: Iterable[object]) -> str:
    h = hashlib.sha256()
    for value in values:
        h.update(encode(value))
    return h.hexdigest()


def _columns(conn: sqlite3.Connection, table: str) -> list[str]:
    return [str(row[1]) for row in conn.execute(f"PRAGMA table_info({table})")]


def _tables(conn: sqlite3.Connection) -> set[str]:
    return {str(row[0]) for row in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}


def part_name(table: str, column: str) -> str:
    """How a refusal names a part: meta 'epsilon', episodes.v_lb, points.s_0."""
    return f"meta {column!r}" if table == "meta" else f"{table}.{column}"


def _small_parts(conn: sqlite3.Connection, present: set[str]) -> dict[str, str]:
    """Every meta key and every column of trajectories, episodes, (a run on a robot) robot_episodes and (a policy L
    chosen from the run's data) lipschitz_choices, hashed whole."""
    parts: dict[str, str] = {}
    if "meta" in present:
        for key, value in conn.execute("SELECT key, value FROM meta ORDER BY key"):
            parts[part_name("meta", str(key))] = _digest((key, value))
    for table in ("trajectories", "episodes", "robot_episodes", "lipschitz_choices"):
        if table not in present:
            continue
        for column in _columns(conn, table):
            rows = conn.execute(f'SELECT "{column}" FROM {table} ORDER BY {_ORDER[table]}')
            parts[part_name(table, column)] = _digest(row[0] for row in rows)
    return parts


def _points_chains(conn: sqlite3.Connection, chains: Mapping[str, str], start: int) -> tuple[dict[str, str], int]:
    """Each points column's chain extended from trajectory ``start`` to the last stored; and how many that is."""
    columns = _columns(conn, "points")
    out = {part_name("points", c): chains.get(part_name("points", c), _EMPTY) for c in columns}
    stored = int(conn.execute("SELECT COALESCE(MAX(trajectory) + 1, 0) FROM points").fetchone()[0])
    selected = ", ".join(f'"{c}"' for c in columns)
    for trajectory in range(start, stored):
        rows = conn.execute(f"SELECT {selected} FROM points WHERE trajectory = ? ORDER BY step", (trajectory,))
        block = list(zip(*rows.fetchall(), strict=True)) or [() for _ in columns]
        for column, values in zip(columns, block, strict=True):
            name = part_name("points", column)
            link = hashlib.sha256(bytes.fromhex(out[name]) + bytes.fromhex(_digest(values)))
            out[name] = link.hexdigest()
    return out, stored


def run_digest(parts: Mapping[str, str]) -> str:
    """The one digest of the whole file: SHA-256 over every part's name and digest, in name order."""
    return _digest(item for name in sorted(parts) for item in (name, parts[name]))


def compute_parts(conn: sqlite3.Connection) -> dict[str, str]:
    """Every part's digest from scratch (the check), with the points chains' length and the run digest."""
    present = _tables(conn)
    parts = _small_parts(conn, present)
    if "points" in present:
        chains, through = _points_chains(conn, {}, 0)
        parts.update(chains)
        parts[THROUGH_PART] = str(through)
    parts[RUN_PART] = run_digest(parts)
    return parts


def recorded_parts(conn: sqlite3.Connection) -> dict[str, str] | None:
    """The seal as written, or None for a file without one (from before seals)."""
    if SEAL_TABLE not in _tables(conn):
        return None
    return {str(part): str(digest) for part, digest in conn.execute(f"SELECT part, sha256 FROM {SEAL_TABLE}")}


def write_seal(conn: sqlite3.Connection) -> str:
    """Seal the file as it stands, inside the caller's write transaction (so the seal commits with the data);
    the points chains are extended from where the last seal left them. Returns the run digest."""
    present = _tables(conn)
    recorded = recorded_parts(conn) or {}
    if SEAL_TABLE not in present:
        conn.execute(f"CREATE TABLE {SEAL_TABLE} (part TEXT PRIMARY KEY, sha256 TEXT NOT NULL)")
    parts = _small_parts(conn, present)
    if "points" in present:
        start = int(recorded.get(THROUGH_PART, "0"))
        chains, through = _points_chains(conn, recorded, start)
        if any(name not in recorded for name in chains):  # a column added since (an upgrade): all chains anew
            chains, through = _points_chains(conn, {}, 0)
        parts.update(chains)
        parts[THROUGH_PART] = str(through)
    parts[RUN_PART] = run_digest(parts)
    conn.execute(f"DELETE FROM {SEAL_TABLE}")
    conn.executemany(f"INSERT INTO {SEAL_TABLE} VALUES (?, ?)", parts.items())
    return parts[RUN_PART]


@dataclass(frozen=True)
class SealCheck:
    """What a check of the seal found: ``digest`` is the run digest the file records ("" when unsealed);
    ``mismatches`` names every part that no longer matches (empty: intact)."""

    digest: str
    mismatches: tuple[str, ...]

    @property
    def sealed(self) -> bool:
        return bool(self.digest)

    def describe(self) -> str:
        if not self.sealed:
            return "UNSEALED: nothing shows the file unchanged since its run (its next write seals it)"
        return f"sealed, digest {self.digest[:16]}..."


def check_seal(conn: sqlite3.Connection) -> SealCheck:
    """Recompute every part and compare it with the seal; call inside one read transaction."""
    recorded = recorded_parts(conn)
    if recorded is None:
        return SealCheck("", ())
    found = compute_parts(conn)
    mismatches = []
    for name in sorted((set(recorded) | set(found)) - {RUN_PART}):
        if name not in recorded:
            mismatches.append(f"{name} (not sealed: added after the run)")
        elif name not in found:
            mismatches.append(f"{name} (removed)")
        elif recorded[name] != found[name]:
            mismatches.append(name)
    if not mismatches and recorded.get(RUN_PART) != run_digest({k: v for k, v in recorded.items() if k != RUN_PART}):
        mismatches.append(f"the seal's own digest ({SEAL_TABLE}.{RUN_PART})")
    return SealCheck(recorded.get(RUN_PART, ""), tuple(mismatches))


def check_file(path: Path) -> SealCheck | None:
    """The seal check of a file the store refuses to open (its format or version edited): what changed, or None
    when the file is no SQLite file with a seal to check."""
    with suppress(sqlite3.Error), closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as conn:
        with conn:
            found = check_seal(conn)
        return found if found.sealed else None
    return None
