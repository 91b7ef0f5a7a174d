"""Shared test fixtures."""
from __future__ import annotations

import weakref

import can
import pytest

# Every python-can bus created during the tests, so a test that leaves one open fails
# (style guide: tests/). Recorded at construction instead of scanning the heap, which
# cost ~0.2 s per test.
_created_buses: "weakref.WeakSet[can.BusABC]" = weakref.WeakSet()
_original_bus_init = can.BusABC.__init__


def _recording_init(self, *args, **kwargs):
    _original_bus_init(self, *args, **kwargs)
    _created_buses.add(self)


can.BusABC.__init__ = _recording_init


@pytest.fixture(autouse=True)
def _no_bus_left_open():
    """Fail a test that leaves a python-can bus open (and close it)."""
    before = set(_created_buses)
    yield
    open_buses = [
        bus for bus in list(_created_buses)
        if bus not in before and not getattr(bus, "_is_shutdown", True)
    ]
    for bus in open_buses:
        bus.shutdown()
    assert not open_buses, f"test left {len(open_buses)} CAN bus(es) open: {open_buses}"
