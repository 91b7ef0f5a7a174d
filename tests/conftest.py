"""Shared test fixtures."""
from __future__ import annotations

import can
import pytest

# Every python-can bus created during the current test, so a test that leaves one open
# fails (style guide: tests/). Recorded at construction instead of scanning the heap
# (which cost ~0.2 s per test); held strongly so a bus dropped without shutdown() is
# still seen.
_created_buses: list[can.BusABC] = []
_original_bus_init = can.BusABC.__init__


def _recording_init(self, *args, **kwargs):
    _original_bus_init(self, *args, **kwargs)
    _created_buses.append(self)


can.BusABC.__init__ = _recording_init


@pytest.fixture(autouse=True)
def _no_bus_left_open():
    """Fail a test that leaves a python-can bus open (and close it)."""
    _created_buses.clear()
    yield
    open_buses = [bus for bus in _created_buses if not getattr(bus, "_is_shutdown", True)]
    _created_buses.clear()
    for bus in open_buses:
        bus.shutdown()
    assert not open_buses, f"test left {len(open_buses)} CAN bus(es) open: {open_buses}"
