"""Opening CAN buses for the HIL nodes, the python-can way.

Bus selection follows python-can (``can/util.py`` ``load_config``): explicit arguments
first, then the ``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment variables, then the
python-can configuration file. Every node opens its own bus object: on python-can's
``virtual`` interface, bus objects on one channel name see each other's frames (never
their own), exactly like sockets on one SocketCAN ``vcan`` device.
"""
from __future__ import annotations

import errno
import itertools
import os
from dataclasses import dataclass

import can

from firmware_sim import can_bus, errors as ecu_errors
from hil.errors import HilError

#: Interface used when neither the arguments, the environment nor a config file name one.
DEFAULT_INTERFACE = "virtual"
#: Channel used when nothing names one (the SocketCAN device of the README).
DEFAULT_CHANNEL = "vcan0"

_private_channel_numbers = itertools.count()


class BusOpenError(HilError, ecu_errors.BusOpenError):
    """A CAN bus could not be opened (unknown interface, missing device, no permission):
    the ECU's error (``firmware_sim.errors.BusOpenError``) in the HIL's hierarchy."""


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
    """Interface and channel after python-can's precedence (`can.util.load_config`, whole:
    arguments, ``can.rc``, the ``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment, the config
    files ``~/can.conf``, ``/etc/can.conf``, ``~/.can``, ``~/.canrc``); only what none of
    them names falls back to :data:`DEFAULT_INTERFACE` / :data:`DEFAULT_CHANNEL`. So a
    ``~/.canrc`` that names only ``channel = vcan1`` gives ``virtual:vcan1``.

    Raises:
        BusOpenError: the configuration names an interface python-can does not know, or
            cannot be read.
    """
    given: dict[str, str] = {}
    if interface:
        given["interface"] = interface
    if channel:
        given["channel"] = channel
    try:
        try:
            config = can.util.load_config(config=given)
        except can.CanInterfaceNotImplementedError:
            if _named_interface(given) is not None:
                raise  # a name python-can does not know: not ours to replace
            # Nothing names an interface: the default, as the lowest-priority source
            # (load_config's first source is the dict given; nothing else named one).
            config = can.util.load_config(config={**given, "interface": DEFAULT_INTERFACE})
    except (can.CanError, ValueError, TypeError, OSError) as e:
        raise BusOpenError(f"cannot open CAN bus: {e} (from the options, $CAN_INTERFACE / "
                           "$CAN_CHANNEL and python-can's config files)") from e
    resolved_channel = config.get("channel")
    if resolved_channel in (None, ""):
        resolved_channel = DEFAULT_CHANNEL
    return BusConfig(str(config["interface"]), str(resolved_channel))


def _named_interface(given: dict[str, str]) -> str | None:
    """The interface some python-can configuration source names, None when none does."""
    sources = (given, can.rc, can.util.load_environment_config(), can.util.load_file_config())
    for source in sources:
        name = source.get("interface") or source.get("bustype")
        if name:
            return str(name)
    return None


def private_virtual_channel(prefix: str = "hil") -> str:
    """A virtual channel name no other run in this process uses, so concurrent or
    consecutive in-process runs (tests, ``make run``) never hear each other."""
    return f"{prefix}-{os.getpid()}-{next(_private_channel_numbers)}"


def open_bus(config: BusConfig, **kwargs: object) -> can.BusABC:
    """Open one bus object on ``config`` (one per node): ``firmware_sim.can_bus.open_bus``,
    the ECU's, with the HIL's error and its SocketCAN hint.

    ``kwargs`` go to ``can.Bus`` (e.g. ``can_filters``). Own frames are not received
    (python-can's default), as on a real controller's CAN port.

    Raises:
        BusOpenError: naming the interface and channel, wrapping python-can's error.
    """
    try:
        return can_bus.open_bus(config.interface, config.channel, **kwargs)
    except ecu_errors.BusOpenError as e:
        reason = e.__cause__  # python-can's error
        raise BusOpenError(f"cannot open CAN bus {config.describe()}: {reason}"
                           f"{socketcan_hint(config, reason)}") from reason


def socketcan_hint(config: BusConfig, error: BaseException | None = None) -> str:
    """Why a SocketCAN channel may not open, telling "no CAN in this kernel" (the socket
    family is refused, EAFNOSUPPORT, or there is no ``/proc/net/can``: a container or a
    kernel without the modules; user-mode Linux gives one, docs/vcan.md) from "no such
    device" (ENODEV: the kernel speaks CAN, the channel is missing: create it); empty for
    other interfaces."""
    if config.interface != "socketcan":
        return ""
    code = getattr(error, "errno", None) or getattr(getattr(error, "__cause__", None), "errno", None)
    if code == errno.EAFNOSUPPORT or (code != errno.ENODEV and not os.path.exists("/proc/net/can")):
        return (" (this kernel has no SocketCAN, no CAN socket family; load the modules with "
                "`sudo modprobe vcan` on a host that has them, or run the HIL on a real vcan0 "
                "inside user-mode Linux: make run-uml, docs/vcan.md; or use --interface "
                "virtual)")
    if code == errno.ENODEV or not os.path.exists(f"/sys/class/net/{config.channel}"):
        return (f" (the kernel speaks CAN but there is no device {config.channel}: create it "
                f"with: sudo ip link add dev {config.channel} type vcan && sudo ip link set up "
                f"{config.channel})")
    return f" (is {config.channel} up? sudo ip link set up {config.channel})"
