"""Shared test fixtures."""
from __future__ import annotations

import gc

import pytest


@pytest.fixture(autouse=True)
def _no_bus_left_open():
    """Fail a test that leaves a python-can bus open (style guide: tests/)."""
    yield
    try:
        import can
    except ImportError:  # pragma: no cover
        return
    gc.collect()
    open_buses = [
        obj for obj in gc.get_objects()
        if isinstance(obj, can.BusABC) and not getattr(obj, "_is_shutdown", True)
    ]
    for bus in open_buses:
        bus.shutdown()
    assert not open_buses, f"test left {len(open_buses)} CAN bus(es) open: {open_buses}"
