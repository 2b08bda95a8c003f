"""Link shaping for testbed hosts: the `tc` commands that cap one direction of a veth link.

A host's link is a veth pair: `eth0` inside the host's namespace and a port on the testbed bridge.
Egress of `eth0` is the host's uplink, egress of the bridge port its downlink; each direction is
capped on its own egress, where the kernel queues packets. The cap is an htb class (rate = ceil)
over a short pfifo: htb handles any packet size and its rate can be changed in place
(`tc class change`) while traffic flows, which is what the bandwidth-glitch experiments need.

The leaf queue is sized to about `QUEUE_DELAY_S` at the capped rate so a full queue adds a bounded
delay (a real uplink's buffer, not the 1000-packet default that would add seconds at 1 Mbit/s);
TCP sees drops when it overshoots and settles at the cap. netem is not used (not available on
every kernel); extra latency comes from the cloud daemon's fault injection instead.

This module only builds argument lists and parses `tc` output; the testbed runs them.
"""

from __future__ import annotations

import math
import re

from common.errors import UserError

MIN_RATE_MBIT = 0.01
MAX_RATE_MBIT = 100_000.0
# Queue at the cap: about this much delay when full, never fewer than MIN_QUEUE_PACKETS.
QUEUE_DELAY_S = 0.1
MIN_QUEUE_PACKETS = 8
PACKET_BYTES = 1514
ROOT_HANDLE = "1:"
CLASS_ID = "1:1"
LEAF_HANDLE = "10:"

_RATE_RE = re.compile(r"\brate (\d+(?:\.\d+)?)([KMG]?)bit\b")
_RATE_UNIT = {"": 1e-6, "K": 1e-3, "M": 1.0, "G": 1e3}


def check_rate(mbit: float | None, what: str) -> float | None:
    """Validate a rate in Mbit/s (None means unlimited)."""
    if mbit is None:
        return None
    if not math.isfinite(mbit) or not MIN_RATE_MBIT <= mbit <= MAX_RATE_MBIT:
        raise UserError(
            f"{what} {mbit:g} Mbit/s is out of range: use {MIN_RATE_MBIT:g} to {MAX_RATE_MBIT:g}"
        )
    return mbit


def _kbit(mbit: float) -> str:
    # tc's "kbit" is 1000 bit/s; an integer keeps the command exact and readable.
    return f"{max(1, round(mbit * 1000))}kbit"


def queue_packets(mbit: float) -> int:
    """Leaf queue length in packets for a link capped at `mbit`."""
    bytes_per_s = mbit * 1e6 / 8
    return max(MIN_QUEUE_PACKETS, math.ceil(bytes_per_s * QUEUE_DELAY_S / PACKET_BYTES))


def class_args(dev: str, mbit: float, verb: str) -> list[str]:
    """`tc class <verb>` arguments for the capping class."""
    rate = _kbit(mbit)
    return [
        *("class", verb, "dev", dev, "parent", ROOT_HANDLE, "classid", CLASS_ID),
        *("htb", "rate", rate, "ceil", rate),
    ]


def install_commands(dev: str, mbit: float) -> list[list[str]]:
    """Commands that put a fresh cap on `dev` (its root qdisc must be the default one)."""
    return [
        ["qdisc", "add", "dev", dev, "root", "handle", ROOT_HANDLE, "htb", "default", "1"],
        class_args(dev, mbit, "add"),
        [
            *("qdisc", "add", "dev", dev, "parent", CLASS_ID, "handle", LEAF_HANDLE),
            *("pfifo", "limit", str(queue_packets(mbit))),
        ],
    ]


def change_commands(dev: str, mbit: float) -> list[list[str]]:
    """Commands that move an installed cap to a new rate without flushing its queue."""
    return [
        class_args(dev, mbit, "change"),
        [
            *("qdisc", "change", "dev", dev, "parent", CLASS_ID, "handle", LEAF_HANDLE),
            *("pfifo", "limit", str(queue_packets(mbit))),
        ],
    ]


def remove_command(dev: str) -> list[str]:
    """Command that drops the cap (the device falls back to its default qdisc)."""
    return ["qdisc", "del", "dev", dev, "root"]


def has_cap(qdisc_show: str) -> bool:
    """True when `tc qdisc show dev X` output has our htb root."""
    return any(
        line.startswith(f"qdisc htb {ROOT_HANDLE}") and " root " in line
        for line in qdisc_show.splitlines()
    )


def parse_class_rate_mbit(class_show: str) -> float | None:
    """The rate of our class from `tc class show dev X` output, in Mbit/s (None if absent)."""
    for line in class_show.splitlines():
        if line.startswith(f"class htb {CLASS_ID} "):
            match = _RATE_RE.search(line)
            if match:
                return float(match.group(1)) * _RATE_UNIT[match.group(2)]
    return None
