"""The registry's views as rich tables, for `elasticfog routes|deployments|robots|events|watch`
(`registry.views_cli`): a table per view and the `watch` screen. Apart from the commands so that
building the CLI (`elasticfog --help`) does not import the tables. Routing is per (robot,
service): when the rows hold several services, the routes, robots, events and profiles tables
show a service column (the deployments table always does).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from datetime import datetime
from typing import TYPE_CHECKING, Any

from rich.console import Group
from rich.table import Table
from rich.text import Text

DIGEST_SHOWN_CHARS = 12

if TYPE_CHECKING:
    from common.wire.registry import DeploymentRow, EventRow, ProfileRow, RobotRow, RouteRow


# -- tables -------------------------------------------------------------------------------------
def _clock(ts: float | None) -> str:
    if ts is None:
        return "-"
    return datetime.fromtimestamp(ts).strftime("%H:%M:%S")


def _ago(ts: float | None, now: float) -> str:
    if ts is None:
        return "-"
    age = max(0.0, now - ts)
    if age < 120:
        return f"{age:.0f} s ago"
    if age < 7200:
        return f"{age / 60:.0f} min ago"
    return f"{age / 3600:.0f} h ago"


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1000:.1f} ms"


def _window(row: RobotRow) -> Text:
    """`<stat> of the window / bound`, red when the bound is broken."""
    if row.window_stat_s is None or row.bound_s is None:
        bound = _ms(row.bound_s)
        return Text(f"- / {bound} {row.bound_stat}", style="dim")
    broken = row.window_stat_s > row.bound_s
    text = f"{_ms(row.window_stat_s)} / {_ms(row.bound_s)} {row.bound_stat} (n={row.window_len})"
    return Text(text, style="red" if broken else "green")


def _table(title: str, *columns: str) -> Table:
    table = Table(title=title, title_justify="left", header_style="bold")
    for column in columns:
        table.add_column(column)
    return table


def _services(rows: Sequence[Any]) -> bool:
    """Whether `rows` name more than one service (then a table shows a service column)."""
    return len({r.service for r in rows}) > 1


def _service(row: Any) -> str:
    return row.service or "-"


def routes_table(rows: Sequence[RouteRow], now: float) -> Table:
    """Robot (and service) → deployment (and its round-robin pool, if any), epoch, since when
    and why."""
    pooled = any(len(r.pool) > 1 for r in rows)
    several = _services(rows)
    columns = [
        "robot",
        *(["service"] if several else []),
        "deployment",
        *(["pool"] if pooled else []),
        "epoch",
        "since",
        "reason",
    ]
    table = _table("routes", *columns)
    for r in rows:
        pool = [", ".join(r.pool) or "-"] if pooled else []
        table.add_row(
            r.robot,
            *([_service(r)] if several else []),
            r.deployment or Text("local", style="yellow"),
            *pool,
            str(r.epoch),
            f"{_clock(r.since)} ({_ago(r.since, now)})",
            r.reason,
        )
    return table


def deployments_table(rows: Sequence[DeploymentRow], now: float) -> Table:
    """Deployments: alive, load against capacity, per-robot states, model."""
    table = _table(
        "deployments",
        "deployment",
        "alive",
        "service",
        "load",
        "capacity",
        "robots",
        "model",
        "last seen",
    )
    for d in rows:
        refused = d.extra.get("refused")
        if refused:
            alive: str | Text = Text(f"refused: {refused}", style="red")
        elif d.alive:
            alive = Text("draining" if d.extra.get("draining") else "yes", style="green")
        else:
            alive = Text("no", style="dim")
        full = d.capacity > 0 and d.load >= d.capacity
        epochs = d.extra.get("epochs", {})
        states = ", ".join(
            f"{robot}: {state.value}@{epochs.get(robot, '?')}"
            for robot, state in sorted(d.states.items())
        )
        table.add_row(
            d.id,
            alive,
            d.service or "-",
            Text(str(d.load), style="red") if full else str(d.load),
            str(d.capacity) if d.capacity else "-",  # 0: not reported, never counted full
            states or "-",
            (d.model_digest or "-")[:DIGEST_SHOWN_CHARS],
            _ago(d.last_seen, now),
        )
    return table


def robots_table(rows: Sequence[RobotRow], now: float, title: str = "robots") -> Table:
    """Robots (a row per service each uses): deployment, its state, epoch, latency window
    against the bound, cut chosen, and the reason of the robot's last route change."""
    several = _services(rows)
    table = _table(
        title,
        "robot",
        *(["service"] if several else []),
        "alive",
        "deployment",
        "state",
        "epoch",
        "window vs bound",
        "cut",
        "timeouts",
        "reason",
    )
    for r in rows:
        state = str(r.extra.get("state", "-"))
        style = {"service": "green", "draining": "yellow", "local": "yellow"}.get(state, "")
        table.add_row(
            r.id,
            *([_service(r)] if several else []),
            Text("yes", style="green") if r.alive else Text("no", style="dim"),
            r.deployment or Text("local", style="yellow"),
            Text(state, style=style),
            str(r.epoch),
            _window(r),
            r.action or "-",
            str(r.extra.get("consecutive_timeouts", 0)),
            r.reason or "-",
        )
    return table


def events_table(rows: Sequence[EventRow], now: float) -> Table:
    """The event log, oldest first."""
    several = _services(rows)
    columns = ["seq", "time", *(["service"] if several else []), "kind", "robot", "deployment"]
    table = _table("events", *columns, "epoch", "reason")
    for e in rows:
        table.add_row(
            str(e.seq),
            _clock(e.at),
            *([_service(e)] if several else []),
            e.kind,
            e.robot or "-",
            e.deployment or "-",
            "-" if e.epoch is None else str(e.epoch),
            e.reason,
        )
    return table


def profiles_table(rows: Sequence[ProfileRow], now: float) -> Table:
    """Probe profiles per robot × deployment (× service)."""
    several = _services(rows)
    columns = ["robot", *(["service"] if several else []), "deployment"]
    table = _table("profiles", *columns, "n", "median", "p95", "max", "updated")
    for p in rows:
        table.add_row(
            p.robot,
            *([_service(p)] if several else []),
            p.deployment,
            str(p.samples),
            _ms(p.median_s),
            _ms(p.p95_s),
            _ms(p.max_s),
            _ago(p.updated_at, now),
        )
    return table


def watch_screen(where: str, rows: Sequence[RobotRow], error: str | None, now: float) -> Group:
    """The `watch` screen: a title line (`where`: the fleet and its endpoint) and the robots
    table."""
    head = Text(f"{where}  {_clock(now)}", style="bold")
    if error is not None:
        head.append(f"  {error}", style="red")
    return Group(head, robots_table(rows, now, title=""))


TABLES: dict[str, Callable[[Sequence[Any], float], Table]] = {
    "routes": routes_table,
    "deployments": deployments_table,
    "robots": robots_table,
    "events": events_table,
    "profiles": profiles_table,
}
