"""`elasticfog bench nav`: the navigation assistant paper's Tables III-V and Figs. 8-9.

Tables III and IV run on the testbed: for each resolution a fleet serving zoo:stereo (split with
segments, so option 3 has its cut 0 → points segment) on one cloud daemon (`edge-1`), and the
robot daemon on the `robot` host with `stereo:world` frames, its host held at `robot_cpu` of a
core and its uplink capped at `uplink_mbit`. Each option is one robot run of N frames at full
speed (no --fps, one frame in flight): the update frequency is the frames it completes per
second, t_o / t_p / t_c / t_f the means of its telemetry's transfer, cloud, robot compute and
whole-frame times (`nav_rows`). `elastic` is the runtime's learner over the whole suffixes
(options 1, 2 and 4 are among them); `elastic-segments` the same learner with the split's
segments among its actions too (option 3 is one), as the runtime runs it on this fleet.

Table V (`--table5`): `sim` (the default) runs afterwards in the in-process closed loop
(`nav_loop`), in simulated time, each frame's latency drawn from the t_f samples just measured
for its option and resolution; `live` drives the maneuvers with the robot daemon itself on the
same fleet, one run per maneuver in real time, after the option runs of each resolution
(`nav_live`). Both take the assistant's T_dead from `--t-dead` (default the assistant's 1 s):
past it d_coll is not trusted and the robot is braked to rest, so a T_dead under the measured
latencies keeps the assisted robot still and its zero collisions say nothing.

The JSON contract (`public`) is the result rows and the fidelity rows (`nav_fidelity`: what each
image codec does to d_coll and the disparity map on rendered frames and the Motorcycle pair, and
whether the default fidelity bound admits it, measured in-process at each resolution); with
`--workdir` the whole result (settings, rows, details with each maneuver's outcome) is also kept
there as `RESULT_FILE`.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from . import nav_fidelity, nav_live
from .fleet import ROBOT_ID, FleetSpec
from .nav_loop import LoopResult, fig8, table5
from .nav_rows import (
    DEFAULT_T_DEAD_S,
    ELASTIC,
    ELASTIC_SEGMENTS,
    NO_TIMING,
    OFF,
    TABLE5_LIVE,
    TABLE5_SIM,
    Option,
    Timing,
    check_t_dead,
    contract_row,
    resolution_label,
    robot_policy,
    timing,
)
from .options import BenchOptions, open_fleet
from .report import fmt, md_table, save_plot, use_agg
from .stats import between, by_frame, lost_frames

MODEL = "zoo:stereo"
SOURCE = "stereo:world"
RESOLUTIONS = ((320, 240), (640, 480))
DEFAULT_UPLINK_MBIT = 100.0
"""Near what 802.11ac WiFi (the paper's Tables III-IV) delivers to one robot in practice."""
FULL_FRAMES, QUICK_FRAMES = 30, 10
FULL_WARMUP, QUICK_WARMUP = 5, 3
FULL_LAPS, QUICK_LAPS = 10, 1
LOOP_OPTIONS: tuple[Option, ...] = (1, 4, ELASTIC, ELASTIC_SEGMENTS, OFF)
"""Driven in the closed loop (the paper's Table V: options 1 and 4, and the assistant off)."""
DEADLINE_S = 30.0
"""Far above option 4 at 640x480 on half a core: every option is measured, not cut off."""
CLOUD_THREADS = 2
CALIBRATION_FRAMES = 1
FIDELITY_FRAMES = 4
"""Rendered frames the fidelity rows are measured on per resolution (and the Motorcycle pair)."""
"""The robot measures its crossings' codecs at start on this many rendered frames: d_coll is
no classifier output, so they cross lossless whatever is measured, and at 640x480 the default
eight pairs (rendered, then every cut's codecs) outlast the start-up wait."""
RUN_SLACK_S = 180.0
HOSTS = ("registry", "robot", "edge-1", "bench")
PAPER_TABLE3_HZ = {
    (1, "320x240"): 12.55, (1, "640x480"): 5.72,
    (2, "320x240"): 8.14, (2, "640x480"): 2.29,
    (3, "320x240"): 7.48, (3, "640x480"): 2.16,
    (4, "320x240"): 7.15, (4, "640x480"): 2.61,
}  # fmt: skip
PAPER_TABLE5 = {(1, "640x480"): 7, (4, "640x480"): 32, (1, "320x240"): 38, (4, "320x240"): 31}
"""Collisions over 70 maneuvers."""
RESULT_FILE = "nav-result.json"
"""The whole result in `--workdir` (the JSON contract prints the rows only)."""


@dataclass(frozen=True)
class NavSettings:
    """What `bench nav` runs beyond the shared bench options."""

    resolutions: tuple[tuple[int, int], ...] = RESOLUTIONS
    options: tuple[Option, ...] = (1, 2, 3, 4, ELASTIC, ELASTIC_SEGMENTS, OFF)
    uplink_mbit: float = DEFAULT_UPLINK_MBIT
    laps: int | None = None
    """Laps of the 7-maneuver circuit; None: 10, 1 with --quick."""
    table5: str = TABLE5_SIM
    """Table V in the in-process loop (`sim`) or driven by the robot daemon (`live`)."""
    t_dead_s: float = DEFAULT_T_DEAD_S
    """The assistant's T_dead in Table V, both modes (`--t-dead`)."""


def _fleet_spec(fleet: str, size: tuple[int, int]) -> FleetSpec:
    return FleetSpec(
        fleet=fleet,
        clouds=("edge-1",),
        model=MODEL,
        input_shape=(3, size[1], size[0]),
        deadline_s=DEADLINE_S,
        cloud_threads=CLOUD_THREADS,
        changes={
            "cuts": {"segments": True},
            "machines": {ROBOT_ID: {"source": SOURCE}},
            "fidelity": {"calibration_frames": CALIBRATION_FRAMES},
        },
    )


Measured = dict[tuple[Option, str], dict[str, Any]]
"""Tables III-IV per (option, resolution label): {"timing", "lost", "actions", "fallbacks"}."""
Driven = dict[tuple[Option, str], nav_live.LiveRuns]
"""Table V driven by the robot daemon per (option, resolution label)."""


def measure(
    options: BenchOptions, settings: NavSettings, frames: int, warmup: int, laps: int
) -> tuple[Measured, Driven]:
    """Tables III-IV on the testbed: {(option, resolution): {"timing", "lost", "actions"}};
    with `--table5 live` also Table V driven by the robot daemon, {(option, resolution):
    LiveRuns}."""
    measured = [o for o in settings.options if o != OFF]
    driven = _loop_options(settings) if settings.table5 == TABLE5_LIVE else []
    out: Measured = {}
    live: Driven = {}
    if not measured and not driven:
        return out, live
    with open_fleet(options, hosts=HOSTS) as tf:
        for size in settings.resolutions:
            label = resolution_label(size)
            options.log(f"{label}: splitting zoo:stereo and starting the fleet")
            tf.launch(_fleet_spec(tf.next_fleet_name("nav-"), size))
            tf.shape_robot(settings.uplink_mbit)
            for option in measured:
                options.log(f"{label}, option {option}: {frames} frames")
                tf.start_robot(robot_policy(option), frames=frames, cpu_fraction=options.robot_cpu)
                records = by_frame(tf.finish_robot(RUN_SLACK_S + frames * (DEADLINE_S + 1)))
                window = between(records, tf.measure_from + warmup)
                out[(option, label)] = {
                    "timing": timing(window),
                    "lost": len(lost_frames(records, frames)),
                    "actions": dict(Counter(str(r["action"]) for r in window).most_common()),
                    "fallbacks": sum(1 for r in window if r.get("fallback")),
                }
            for option in driven:
                live[(option, label)] = nav_live.drive(
                    tf, option, size, laps, options.robot_cpu, options.log, settings.t_dead_s
                )
    return out, live


def _loop_options(settings: NavSettings) -> list[Option]:
    """The options Table V drives (the paper's 1 and 4, elastic, off), in the asked order."""
    return [o for o in settings.options if o in LOOP_OPTIONS]


def run(options: BenchOptions, settings: NavSettings) -> dict[str, Any]:
    """The whole experiment: {"settings", "results" (contract rows), "details", "plots"}."""
    options.check()
    check_t_dead(settings.t_dead_s)
    frames = options.frames_or(FULL_FRAMES, QUICK_FRAMES)
    warmup = min(QUICK_WARMUP if options.quick else FULL_WARMUP, max(0, frames - 3))
    laps = settings.laps or (QUICK_LAPS if options.quick else FULL_LAPS)
    measured, live = measure(options, settings, frames, warmup, laps)
    fidelity = nav_fidelity.summary(
        [
            row
            for width, height in settings.resolutions
            for row in nav_fidelity.measure(width, height, 1 if options.quick else FIDELITY_FRAMES)
        ]
    )
    if settings.table5 == TABLE5_LIVE:
        # Fig. 9 needs a speed trace, which the robot's outcome files do not carry.
        loop = LoopResult({key: runs.figures for key, runs in live.items()})
        loop.dcoll = fig8(settings.resolutions[-1])
    else:
        latencies = {key: m["timing"].frame_latencies_s for key, m in measured.items()}
        loop = table5(
            settings.resolutions,
            _loop_options(settings),
            latencies,
            laps,
            options.log,
            deadline_s=settings.t_dead_s,
        )
    rows: list[dict[str, Any]] = []
    details: list[dict[str, Any]] = []
    for size in settings.resolutions:
        label = resolution_label(size)
        for option in settings.options:
            m = measured.get((option, label), {})
            figures: Timing = m.get("timing", NO_TIMING)
            loop_figures = loop.figures.get((option, label))
            driven = live.get((option, label))
            lost = m.get("lost", 0) + (driven.lost if driven is not None else 0)
            row = contract_row(option, size, figures, loop_figures, lost)
            rows.append(row)
            detail = {
                "option": option, "resolution": label, "actions": m.get("actions", {}),
                "fallbacks": m.get("fallbacks", 0), "frames": len(figures.frame_latencies_s),
                "distance_m": loop_figures.distance_m if loop_figures else None,
                "min_clearance_m": loop_figures.min_clearance_m if loop_figures else None,
            }  # fmt: skip
            if driven is not None:
                detail["maneuvers"] = driven.maneuvers
            elif (option, label) in loop.maneuvers:
                detail["maneuvers"] = loop.maneuvers[(option, label)]
            details.append(detail)
    result = {
        "settings": {
            "model": MODEL,
            "source": SOURCE,
            "robot_cpu": options.robot_cpu,
            "uplink_mbit": settings.uplink_mbit,
            "frames": frames,
            "warmup_frames": warmup,
            "laps": laps,
            "cloud_threads": CLOUD_THREADS,
            "table5": settings.table5,
            "t_dead_s": settings.t_dead_s,
        },
        "results": rows,
        "fidelity": fidelity,
        "details": details,
        "plots": {"dcoll": loop.dcoll, "speeds": loop.speeds},
    }
    if options.workdir is not None:
        keep_result(result, options.workdir)
    return result


def keep_result(result: dict[str, Any], workdir: Path) -> Path:
    """Write the result less the plots' data to `workdir`/RESULT_FILE: the JSON contract
    carries the rows only, and Table V's distances, clearances and per-maneuver outcomes are
    in `details`."""
    workdir.mkdir(parents=True, exist_ok=True)
    path = workdir / RESULT_FILE
    kept = {key: value for key, value in result.items() if key != "plots"}
    path.write_text(json.dumps(kept, indent=1) + "\n", encoding="utf-8")
    return path


def public(result: dict[str, Any]) -> dict[str, Any]:
    """The JSON contract: {results: [rows], fidelity: [rows]} and nothing else."""
    return {"results": result["results"], "fidelity": result.get("fidelity", [])}


def _find(rows: list[dict[str, Any]], option: Option, label: str) -> dict[str, Any] | None:
    return next((r for r in rows if r["option"] == option and r["resolution"] == label), None)


def markdown(result: dict[str, Any]) -> str:
    """Tables III, IV and V, the paper's figures beside ours where it has them."""
    rows, details, s = result["results"], result["details"], result["settings"]
    labels = list(dict.fromkeys(r["resolution"] for r in rows))
    timed = [o for o in dict.fromkeys(r["option"] for r in rows) if o != OFF]
    out = [
        f"zoo:stereo, `{s['source']}` frames, robot at {s['robot_cpu']:g} core, uplink "
        f"{s['uplink_mbit']:g} Mbit/s, {s['frames']} frames per option ({s['warmup_frames']} "
        "left out), one frame in flight; the paper's figures in brackets."
    ]
    table3 = []
    for option in timed:
        cells = [str(option)]
        for label in labels:
            row = _find(rows, option, label)
            paper = PAPER_TABLE3_HZ.get((option, label))
            cell = fmt(row["update_hz"] if row else None, 2)
            cells.append(cell + (f" ({paper:g})" if paper is not None else ""))
        table3.append(cells)
    if table3:
        out.append(
            "**Table III: update frequency (Hz)**\n\n" + md_table(["option", *labels], table3)
        )
    for label in labels:
        table4 = []
        for option in timed:
            row = _find(rows, option, label)
            detail = next(d for d in details if d["option"] == option and d["resolution"] == label)
            if row is None:
                continue
            actions = ", ".join(f"{a} ×{n}" for a, n in detail["actions"].items()) or "—"
            table4.append(
                [str(option), *(fmt(row[k], 3) for k in ("t_o_s", "t_p_s", "t_c_s", "t_f_s")),
                 row["lost"], actions]
            )  # fmt: skip
        if table4:
            header = ["option", "t_o (s)", "t_p (s)", "t_c (s)", "t_f (s)", "lost", "actions"]
            out.append(f"**Table IV at {label}: mean delays**\n\n" + md_table(header, table4))
    table5_rows = []
    for label in labels:
        for row in (r for r in rows if r["resolution"] == label and r["collisions"] is not None):
            ratio = row["collisions"] / row["maneuvers"] if row["maneuvers"] else None
            paper = PAPER_TABLE5.get((row["option"], label))
            detail = next(
                d for d in details if d["option"] == row["option"] and d["resolution"] == label
            )
            table5_rows.append(
                [label, str(row["option"]), f"{row['collisions']} / {row['maneuvers']}",
                 fmt(ratio, 2), fmt(detail["distance_m"], 2),
                 fmt(detail.get("min_clearance_m"), 3),
                 f"{paper} / 70 ({paper / 70:.2f})" if paper is not None else "—"]
            )  # fmt: skip
    if table5_rows:
        header = [
            "resolution", "option", "collisions", "ratio", "driven (m)", "min clearance (m)",
            "paper",
        ]  # fmt: skip
        how = (
            "the robot daemon over Zenoh, one run per maneuver in real time, 10 fps camera"
            if s.get("table5") == TABLE5_LIVE
            else "closed loop in simulated time, latencies drawn from the measured t_f"
        )
        how += f", T_dead {s.get('t_dead_s', DEFAULT_T_DEAD_S):g} s"
        out.append(
            f"**Table V: collisions per maneuvers** ({how})\n\n" + md_table(header, table5_rows)
        )
    if result.get("fidelity"):
        out.append(
            "**Fidelity: each image codec against raw** (worst frame; admitted by the default "
            "bound: every bin of d_coll within max_output_rel_err of its raw value)\n\n"
            + nav_fidelity.markdown(result["fidelity"])
        )
    return "\n\n".join(out) + "\n"


def plot(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """Fig. 8 (d_coll(K) approaching a wall) and Fig. 9 (joystick vs commanded speed)."""
    use_agg()
    import matplotlib.pyplot as plt

    paths: list[Path] = []
    data = result.get("plots", {})
    if data.get("dcoll"):
        fig, ax = plt.subplots(figsize=(6, 4))
        for profile in data["dcoll"]:
            ax.plot(
                profile["curvatures"],
                profile["distances"],
                marker=".",
                label=f"wall {profile['ahead_m']:.1f} m ahead",
            )
        ax.set_xlabel("curvature K (1/m, > 0 turns left)")
        ax.set_ylabel("d_coll(K) (m)")
        ax.grid(True, alpha=0.3)
        ax.legend()
        ax.set_title("d_coll(K) approaching a wall (Fig. 8)")
        paths.append(save_plot(fig, out_dir / "nav_dcoll.png"))
    speeds = data.get("speeds")
    if speeds:
        fig, ax = plt.subplots(figsize=(9, 3.5))
        ax.plot(speeds["t_s"], speeds["joystick_mps"], label="joystick v_j")
        ax.plot(speeds["t_s"], speeds["sent_mps"], label="commanded v_c")
        ax.set_xlabel("time over one lap's 7 maneuvers (s)")
        ax.set_ylabel("linear speed (m/s)")
        ax.grid(True, alpha=0.3)
        ax.legend()
        ax.set_title(
            f"Joystick vs commanded speed, option {speeds['option']} at {speeds['resolution']} "
            "(Fig. 9)"
        )
        paths.append(save_plot(fig, out_dir / "nav_speed.png"))
    return paths
