"""`bench pool`'s figures: what one robot run against a round-robin pool says, as rows.

A row is one pool size P: the update rate and mean delays over the measured window, figured as
`bench nav` figures them (`nav_rows.timing`: frames completed per second, t_o / t_p / t_c / t_f
from the records' transfer, cloud, robot compute and whole-frame times), who answered each frame
(the record's `deployment`), the frames the robot finished itself by reason, the frames never
reported (lost), and the two checks of "each frame computed once": no frame has two records, and
the frames each cloud daemon says it answered for the robot (its per-robot `served` count, read
from its probe reply) are the frames the robot's telemetry says it answered, and add up to the
frames the robot offloaded. `p_needed` is the paper's sizing rule p >= ceil(t_p / T_f), t_p
measured by the run of the smallest pool and T_f the camera period.

The kill run's summary splits the same figures at the frame where one member was killed.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from common.errors import UserError
from common.wire.telemetry import ACTION_ROBOT

from .nav_rows import resolution_label, timing, update_hz
from .stats import Record, between, by_frame, lost_frames

ROW_KEYS = (
    "pool_size",
    "resolution",
    "max_in_flight",
    "pool",
    "frames",
    "update_hz",
    "t_o_s",
    "t_p_s",
    "t_c_s",
    "t_f_s",
    "p_needed",
    "answered_by",
    "fallbacks",
    "lost",
    "duplicates",
    "offloaded",
    "served_by_cloud",
    "served_sum",
    "computed_in_log",
    "each_frame_once",
)
"""The keys of a result row, in order."""
_COMPUTED_LINE = re.compile(r"(?P<deployment>\S+): (?P<frames>\d+) request\(s\) computed in ")
"""A cloud daemon's exit summary (`cloudd.batch_stats.BatchStats.log_summary`)."""


def parse_sizes(text: str, *, hosts: int, standby: bool) -> list[int]:
    """'1,2,3' -> [1, 2, 3] (sorted, each once); a pool needs a cloud host per member, and the
    kill run (`standby`) one more beyond the largest pool."""
    sizes: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        if not part.isdigit() or int(part) < 1:
            raise UserError(f"--sizes: {part!r} is not a pool size (a whole number from 1)")
        sizes.add(int(part))
    if not sizes:
        raise UserError("--sizes: expected at least one pool size, e.g. 1,2,3")
    most = hosts - 1 if standby else hosts
    if max(sizes) > most:
        why = (
            f"the testbed has {hosts} cloud hosts and the kill run needs one of them as a "
            "standby (--no-kill lifts that)"
            if standby
            else f"the testbed has {hosts} cloud hosts"
        )
        raise UserError(f"--sizes {max(sizes)}: at most {most}: {why}")
    return sorted(sizes)


def p_needed(t_p_s: float | None, fps: float) -> int | None:
    """ceil(t_p / T_f) with T_f = 1 / fps: the deployments that keep up with the camera when each
    computes one frame at a time (None without a measured t_p)."""
    if t_p_s is None:
        return None
    # Rounded first: 0.2 s at 10 fps is 2, not the 3 that 2.0000000000000004 would give.
    return max(1, math.ceil(round(t_p_s * fps, 9)))


def duplicate_frames(records: Iterable[Record]) -> list[int]:
    """Frames with more than one telemetry record (each frame must be finished once)."""
    counts = Counter(r.get("frame") for r in records)
    return sorted(int(f) for f, n in counts.items() if isinstance(f, int) and n > 1)


def answered(record: Record) -> str | None:
    """The deployment whose reply finished this frame; None if the robot finished it."""
    if record.get("fallback") or not record.get("deployment"):
        return None
    return str(record["deployment"])


def answered_by(records: Iterable[Record]) -> dict[str, int]:
    """Frames answered per deployment, by name."""
    counts = Counter(d for d in map(answered, records) if d is not None)
    return dict(sorted(counts.items()))


def fallbacks_by_reason(records: Iterable[Record]) -> dict[str, int]:
    """Offloaded frames the robot finished itself, by reason."""
    counts = Counter(str(r.get("reason")) for r in records if r.get("fallback"))
    return dict(sorted(counts.items()))


def offloaded(records: Iterable[Record]) -> int:
    """Frames the robot sent to the cloud (answered or not)."""
    return sum(1 for r in records if str(r.get("action")) != ACTION_ROBOT)


def parse_computed(log_text: str, deployment: str) -> int | None:
    """Requests `deployment` computed, from its exit summary (None: no summary, e.g. a daemon
    that was killed or computed nothing)."""
    found = None
    for match in _COMPUTED_LINE.finditer(log_text):
        if match["deployment"] == deployment:
            found = int(match["frames"])
    return found


@dataclass(frozen=True)
class PoolRun:
    """What one robot run against a pool left: its telemetry and the deployments' counts."""

    pool_size: int
    max_in_flight: int
    frames: int
    """Frames the robot was asked for (0..frames-1 must each have a record)."""
    measure_from: int
    """The first frame of the measured window (after the CPU quota, the warm-up and the pool)."""
    records: Sequence[Record]
    """Every telemetry record of the run, as written (duplicates included)."""
    pool: Sequence[str] = ()
    """The route's pool as the registry's routes view listed it during the run."""
    served: Mapping[str, int | None] = field(default_factory=dict)
    """Frames each cloud daemon says it answered for the robot (None: it could not be asked)."""
    computed: Mapping[str, int | None] = field(default_factory=dict)
    """Requests each cloud daemon computed, from its exit summary (None: none logged)."""

    @property
    def window(self) -> list[Record]:
        return between(by_frame(self.records), self.measure_from)


def _once(run: PoolRun, records: Sequence[Record]) -> dict[str, Any]:
    """The "each frame once" figures over `records` (a whole run)."""
    dups = duplicate_frames(records)
    by_dep = answered_by(records)
    known = {d: n for d, n in run.served.items() if n is not None}
    # A deployment that counts more than the robot saw answered computed a frame the robot
    # also finished (or one for nobody); fewer, and a reply was used that nobody counted.
    counts_agree = all(by_dep.get(d, 0) == n for d, n in known.items())
    served_sum = sum(known.values()) if len(known) == len(run.served) and known else None
    return {
        "duplicates": dups,
        "offloaded": offloaded(by_frame(records)),
        "served_sum": served_sum,
        "each_frame_once": not dups and counts_agree,
    }


def pool_row(run: PoolRun, size: tuple[int, int], p_needed_ref: int | None) -> dict[str, Any]:
    """One result row (ROW_KEYS): the run's figures; `p_needed_ref` is the sizing rule's answer
    from the reference t_p (the same on every row)."""
    figures = timing(run.window)
    once = _once(run, run.records)
    row = {
        "pool_size": run.pool_size,
        "resolution": resolution_label(size),
        "max_in_flight": run.max_in_flight,
        "pool": list(run.pool),
        "frames": len(run.window),
        "update_hz": figures.update_hz,
        "t_o_s": figures.t_o_s,
        "t_p_s": figures.t_p_s,
        "t_c_s": figures.t_c_s,
        "t_f_s": figures.t_f_s,
        "p_needed": p_needed_ref,
        "answered_by": answered_by(run.window),
        "fallbacks": fallbacks_by_reason(run.window),
        "lost": len(lost_frames(run.records, run.frames)),
        "duplicates": once["duplicates"],
        "offloaded": once["offloaded"],
        "served_by_cloud": dict(run.served),
        "served_sum": once["served_sum"],
        "computed_in_log": dict(run.computed),
        "each_frame_once": once["each_frame_once"],
    }
    assert tuple(row) == ROW_KEYS
    return row


def reference_t_p(runs: Sequence[PoolRun]) -> float | None:
    """t_p of the smallest pool's run (P = 1 by default): one deployment's processing time."""
    if not runs:
        return None
    smallest = min(runs, key=lambda r: r.pool_size)
    return timing(smallest.window).t_p_s


@dataclass(frozen=True)
class KillEvent:
    """Which member was killed, when, and what the registry's route said before and after."""

    primary: str
    killed: str
    kill_frame: int
    """The first frame not yet reported when the member was killed."""
    standby: Sequence[str]
    pool_before: Sequence[str]
    pool_after: Sequence[str]
    repaired_after_s: float | None
    """Seconds from the kill until the route's pool no longer listed the killed member and
    listed a standby (None: not seen within the wait)."""


def kill_summary(run: PoolRun, event: KillEvent) -> dict[str, Any]:
    """The kill run: lost frames, fallbacks and who answered, before and after the kill."""
    window = run.window
    before = between(window, run.measure_from, event.kill_frame)
    after = between(window, event.kill_frame)
    once = _once(run, run.records)
    return {
        "pool_size": run.pool_size,
        "max_in_flight": run.max_in_flight,
        "primary": event.primary,
        "killed": event.killed,
        "killed_primary": event.killed == event.primary,
        "standby": list(event.standby),
        "kill_frame": event.kill_frame,
        "pool_before": list(event.pool_before),
        "pool_after": list(event.pool_after),
        "standby_joined": any(s in event.pool_after for s in event.standby)
        and event.killed not in event.pool_after,
        "repaired_after_s": event.repaired_after_s,
        "frames": len(window),
        "lost": len(lost_frames(run.records, run.frames)),
        "fallbacks": fallbacks_by_reason(window),
        "answered_before": answered_by(before),
        "answered_after": answered_by(after),
        "update_hz_before": update_hz(before),
        "update_hz_after": update_hz(after),
        "duplicates": once["duplicates"],
        "offloaded": once["offloaded"],
        "served_by_cloud": dict(run.served),
        "computed_in_log": dict(run.computed),
        "each_frame_once": once["each_frame_once"],
    }
