"""Keep the CPUs out of their idle states for a timing run (Linux PM QoS), as cyclictest does.

An idle core halts; on this virtual machine (cpuidle driver ``haltpoll``) a halted vCPU
returns its physical core to the host, which runs other work there, and the ECU's next task
starts on cold caches. Measured in ``make timing`` before this request: the C ECU's QP
solve p99 was 0.168 ms with the machine idle and 0.030 ms with a busy loop on every core,
the same QP. Real-time Linux set-ups hold a CPU latency request of 0 us for the whole run
(``/dev/cpu_dma_latency``: the request lasts while the file stays open), so the idle loop
polls instead of halting; the timing benchmark does the same for every ECU alike.
"""
from __future__ import annotations

import struct
from pathlib import Path
from types import TracebackType

#: The PM QoS CPU latency device: write a signed 32-bit latency in microseconds.
CPU_DMA_LATENCY = Path("/dev/cpu_dma_latency")


class CpuLatencyRequest:
    """A context manager holding a CPU latency request of ``max_us`` microseconds.

    ``requested=False``: holds nothing (the machine's idle states). Never raises for an
    unavailable device (not Linux, not root): ``describe()`` then says why, and the run
    goes on with the default idle states.
    """

    def __init__(self, max_us: int = 0, device: Path = CPU_DMA_LATENCY,
                 requested: bool = True) -> None:
        if max_us < 0:
            raise ValueError(f"CPU latency request must be >= 0 us, got {max_us}")
        self.max_us = max_us
        self.device = device
        self.requested = requested
        self._file = None
        self._problem = "not requested (the machine's idle states)"

    def __enter__(self) -> "CpuLatencyRequest":
        if not self.requested:
            return self
        try:
            self._file = self.device.open("wb", buffering=0)
            self._file.write(struct.pack("<i", self.max_us))
            self._problem = ""
        except OSError as e:
            if self._file is not None:
                self._file.close()
                self._file = None
            self._problem = f"not held ({self.device}: {e.strerror or e})"
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        if self._file is not None:
            self._file.close()  # closing the file drops the request
            self._file = None

    @property
    def held(self) -> bool:
        """True while the request is in force."""
        return self._file is not None

    def describe(self) -> str:
        """One line for the report."""
        if self.held:
            return f"held at {self.max_us} us ({self.device}, PM QoS)"
        return self._problem
