"""Opening CAN buses for the HIL nodes, the python-can way.

Bus selection follows python-can (``can/util.py`` ``load_config``): explicit arguments
first, then the ``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment variables, then the
python-can configuration file. Every node opens its own bus object: on python-can's
``virtual`` interface, bus objects on one channel name see each other's frames (never
their own), exactly like sockets on one SocketCAN ``vcan`` device.
"""
from __future__ import annotations

import itertools
import os
from dataclasses import dataclass

import can

from hil.errors import HilError

#: Interface used when neither the arguments, the environment nor a config file name one.
DEFAULT_INTERFACE = "virtual"
#: Channel used when nothing names one (the SocketCAN device of the README).
DEFAULT_CHANNEL = "vcan0"

_private_channel_numbers = itertools.count()


class BusOpenError(HilError):
    """A CAN bus could not be opened (unknown interface, missing device, no permission)."""


@dataclass(frozen=True)
class BusConfig:
    """Which CAN bus a run uses: python-can interface name and channel."""

    interface: str
    channel: str

    @property
    def is_virtual(self) -> bool:
        """True for python-can's in-process ``virtual`` bus (nodes share one process)."""
        return self.interface == "virtual"

    def describe(self) -> str:
        """Human-readable ``interface:channel``."""
        return f"{self.interface}:{self.channel}"


def resolve_bus_config(interface: str | None = None, channel: str | None = None) -> BusConfig:
    """Interface and channel after python-can's precedence: arguments, then the
    ``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment, then the python-can config file,
    then :data:`DEFAULT_INTERFACE` / :data:`DEFAULT_CHANNEL`.

    Raises:
        BusOpenError: the python-can configuration cannot be read.
    """
    given: dict[str, str] = {}
    if interface:
        given["interface"] = interface
    if channel:
        given["channel"] = channel
    try:
        config = can.util.load_config(config=given)
    except (can.CanError, ValueError, NotImplementedError) as e:
        # load_config refuses a config without an interface; fall back to our default.
        config = dict(given)
        if "interface" not in config:
            config["interface"] = os.environ.get("CAN_INTERFACE") or DEFAULT_INTERFACE
        if "channel" not in config and not os.environ.get("CAN_CHANNEL"):
            config["channel"] = DEFAULT_CHANNEL
        if "interface" not in config:
            raise BusOpenError(f"cannot resolve the CAN interface: {e}") from e
    resolved_interface = str(config.get("interface") or DEFAULT_INTERFACE)
    resolved_channel = config.get("channel")
    if resolved_channel in (None, ""):
        resolved_channel = os.environ.get("CAN_CHANNEL") or DEFAULT_CHANNEL
    return BusConfig(resolved_interface, str(resolved_channel))


def private_virtual_channel(prefix: str = "hil") -> str:
    """A virtual channel name no other run in this process uses, so concurrent or
    consecutive in-process runs (tests, ``make run``) never hear each other."""
    return f"{prefix}-{os.getpid()}-{next(_private_channel_numbers)}"


def open_bus(config: BusConfig, **kwargs: object) -> can.BusABC:
    """Open one bus object on ``config`` (one per node).

    ``kwargs`` go to ``can.Bus`` (e.g. ``can_filters``). Own frames are not received
    (python-can's default), as on a real controller's CAN port.

    Raises:
        BusOpenError: naming the interface and channel, wrapping python-can's error.
    """
    try:
        return can.Bus(interface=config.interface, channel=config.channel, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as e:
        hint = ""
        if config.interface == "socketcan":
            hint = (f" (does {config.channel} exist? create it with: sudo ip link add dev "
                    f"{config.channel} type vcan && sudo ip link set up {config.channel})")
        raise BusOpenError(f"cannot open CAN bus {config.describe()}: {e}{hint}") from e
