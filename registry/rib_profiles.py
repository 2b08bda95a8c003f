"""The RIB's profiles table: the latency windows a restarted registry reads back.

`RibProfiles` is the part of `registry.rib.Rib` that reads and writes the `profiles` table (one
row per robot × deployment × source, its samples oldest first), on the store's one connection;
the rest of the RIB (deployments, robots, routes, epochs, events) builds on it. It stands apart
because it is written in bulk on its own schedule (`registry.profile_saver`), never inside a
route's transaction.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass
from typing import Any

from registry.rib_store import RibStore


@dataclass(frozen=True)
class RibProfileRow:
    """Persisted latency samples of one robot × deployment × source (oldest first)."""

    robot: str
    deployment: str
    source: str
    samples: tuple[float, ...]
    updated_at: float

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a JSON view."""
        return {**asdict(self), "samples": list(self.samples)}


class RibProfiles(RibStore):
    """The profiles table of the RIB (see the module docstring)."""

    def save_profile(
        self,
        robot: str,
        deployment: str,
        source: str,
        samples: Iterable[float],
        updated_at: float | None = None,
    ) -> None:
        """Persist a window's samples (oldest first) so a restarted registry keeps its profiles."""
        self.save_profiles([(robot, deployment, source, list(samples), updated_at)])

    def save_profiles(
        self, rows: Iterable[tuple[str, str, str, Sequence[float], float | None]]
    ) -> int:
        """Persist many windows, (robot, deployment, source, samples, updated_at) each, in one
        transaction (a registry of 1,000 robots and 100 deployments saves 100,000 windows every
        few seconds); returns how many were written. Samples are kept to six significant
        digits."""
        now = self._clock()
        written = 0

        def params() -> Iterator[tuple[str, str, str, str, float]]:
            # Made one at a time as sqlite takes them: 100,000 rows are never all in memory, and
            # a bad one raises inside the transaction, which then writes none of them.
            nonlocal written
            for robot, deployment, source, samples, updated_at in rows:
                values = [float(s) for s in samples]
                if not all(math.isfinite(v) and v >= 0 for v in values):
                    raise ValueError(
                        f"profile samples of {robot}/{deployment} must be finite numbers >= 0,"
                        f" got {values!r}"
                    )
                source_s = str(getattr(source, "value", source))
                stamp = now if updated_at is None else updated_at
                written += 1
                yield robot, deployment, source_s, _samples_json(values), stamp

        with self._tx() as conn:
            conn.executemany(
                "INSERT INTO profiles (robot, deployment, source, samples, updated_at)"
                " VALUES (?,?,?,?,?) ON CONFLICT (robot, deployment, source) DO UPDATE SET"
                " samples=excluded.samples, updated_at=excluded.updated_at",
                params(),
            )
        return written

    def profiles(self, robot: str | None = None) -> list[RibProfileRow]:
        """Persisted profiles, optionally of one robot."""
        if robot is None:
            rows = self._query("SELECT * FROM profiles ORDER BY robot, deployment, source")
        else:
            rows = self._query(
                "SELECT * FROM profiles WHERE robot = ? ORDER BY deployment, source", (robot,)
            )
        return [
            RibProfileRow(
                robot=r["robot"],
                deployment=r["deployment"],
                source=r["source"],
                samples=tuple(float(x) for x in json.loads(r["samples"])),
                updated_at=r["updated_at"],
            )
            for r in rows
        ]


def _samples_json(values: Sequence[float]) -> str:
    """A JSON list of latency samples to six significant digits (a microsecond at 100 ms):
    writing every float in full was most of the time of saving 100,000 windows."""
    return "[" + ",".join(["%.6g"] * len(values)) % tuple(values) + "]"
