"""Opening a CAN bus the python-can way, for the ECU and the HIL nodes alike.

`open_bus` is the one call of ``can.Bus`` behind both: arguments first, None falling back
to python-can's configuration (the ``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment, the
config file), and every error python-can raises for a bus that cannot be opened wrapped in
``firmware_sim.errors.BusOpenError``. The ECU's own port (`open_ecu_bus`) first makes
python-can's socketcand interface try one connection, not ten seconds of them: the ECU
retries every second itself (``firmware_sim/bus_quiet.py``).
"""
from __future__ import annotations

import can

from firmware_sim.bus_quiet import quiet_socketcand
from firmware_sim.errors import BusOpenError

#: What python-can raises for a bus it cannot open (an unknown interface, a missing device
#: or server, no permission, an option the interface does not take).
OPEN_ERRORS = (can.CanError, OSError, ValueError, ImportError, NotImplementedError, TypeError)


def open_bus(interface: str | None, channel: str | None, bitrate: int | None = None,
             **kwargs: object) -> can.BusABC:
    """Open one bus object; ``interface`` / ``channel`` None fall back to python-can's
    configuration. ``kwargs`` go to ``can.Bus`` (``can_filters``, a socketcand ``host``).

    Raises:
        BusOpenError: python-can could not open it (the message names interface and
            channel; the python-can error is its ``__cause__``).
    """
    if bitrate is not None:
        kwargs["bitrate"] = bitrate
    try:
        return can.Bus(channel=channel, interface=interface, **kwargs)
    except OPEN_ERRORS as error:
        raise BusOpenError(f"cannot open CAN bus (interface={interface or 'from config'}, "
                           f"channel={channel or 'from config'}): {error}") from error


def open_ecu_bus(interface: str | None, channel: str | None, bitrate: int | None) -> can.BusABC:
    """The ECU's bus (`open_bus`), with python-can's socketcand interface reduced to one
    connection attempt and no log flood: the ECU retries every second (contract).

    Raises:
        BusOpenError: as `open_bus`.
    """
    quiet_socketcand()
    return open_bus(interface, channel, bitrate)
