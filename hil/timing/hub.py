"""A CAN bus between processes over TCP loopback, speaking socketcand's protocol.

The host kernel has no SocketCAN, so for the timing benchmark the ECU and the plant, each
in its own process, talk through python-can's ``socketcand`` interface to this hub on
127.0.0.1 (never any other address). Every client does socketcand's handshake
(``< hi >``, ``< open CHANNEL >`` / ``< ok >``, ``< rawmode >`` / ``< ok >``); each
``< send ID DLC B0 B1 ... >`` it writes is delivered as ``< frame ID SECONDS HEXDATA >``
to every other client on the same channel, never back to the sender, as a CAN controller
does. A client receives frames sent from ``READY_DELAY_S`` after its handshake on (so that
its last ``< ok >`` arrives alone, as python-can's client reads it with one ``recv``).

    python -m hil.timing.hub [--port 0]      # prints "port N", serves until SIGTERM

One thread, one `selectors` loop, TCP_NODELAY on every connection: a frame costs one
``recv`` and one ``send`` per receiver on the hub's side.
"""
from __future__ import annotations

import argparse
import selectors
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field

from hil.errors import HilError

LOOPBACK = "127.0.0.1"
#: Wait after a client's handshake before frames are delivered to it, s.
READY_DELAY_S = 0.1
#: A client whose unparsed input grows beyond this is disconnected (not socketcand).
MAX_PENDING_CHARS = 4096
_SELECT_TIMEOUT_S = 0.05


class HubError(HilError):
    """The hub cannot start (port taken) or was asked for a non-loopback address."""


class ProtocolError(HubError):
    """A client wrote something that is not socketcand's raw-mode protocol."""


@dataclass
class _Client:
    sock: socket.socket
    channel: str | None = None
    raw_mode: bool = False
    ready_at: float = float("inf")
    pending: str = ""
    frames_in: int = 0


@dataclass
class HubStats:
    """Frames received from clients and deliveries made (one per receiving client)."""

    frames_in: int = 0
    deliveries: int = 0
    clients_seen: int = 0
    protocol_errors: list[str] = field(default_factory=list)


def send_to_frame(command: str, timestamp_s: float) -> tuple[str, str]:
    """``"< send 100 8 a 0 ff ... >"`` -> (CAN ID text, ``"< frame ID T HEX >"``).

    Raises:
        ProtocolError: not a ``send`` command, a bad ID, DLC or byte, or a DLC that does
            not match the number of bytes.
    """
    parts = command.strip("<> ").split()
    if len(parts) < 3 or parts[0] != "send":
        raise ProtocolError(f"expected '< send ID DLC BYTES >', got {command!r}")
    can_id, dlc_text, data_text = parts[1], parts[2], parts[3:]
    try:
        int(can_id, 16)
        dlc = int(dlc_text, 16)
        data = bytes(int(b, 16) for b in data_text)
    except ValueError:
        raise ProtocolError(f"bad ID, DLC or data byte in {command!r}") from None
    if len(can_id) not in (3, 8) or dlc != len(data) or dlc > 8:
        raise ProtocolError(f"ID must have 3 or 8 hex digits and DLC ({dlc}) match the "
                            f"{len(data)} data bytes (at most 8) in {command!r}")
    return can_id, f"< frame {can_id} {timestamp_s:.6f} {data.hex()} >"


class LoopbackCanHub:
    """The hub on ``127.0.0.1:port`` (0: a free port, see `port`).

    Raises:
        HubError: a host other than 127.0.0.1, or the port cannot be bound.
    """

    def __init__(self, port: int = 0, host: str = LOOPBACK) -> None:
        if host != LOOPBACK:
            raise HubError(f"the hub serves loopback only ({LOOPBACK}), not {host!r}")
        try:
            self._server = socket.create_server((host, port))
        except OSError as e:
            raise HubError(f"cannot listen on {host}:{port}: {e}") from e
        self._server.setblocking(False)
        self.port: int = self._server.getsockname()[1]
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._server, selectors.EVENT_READ, None)
        self._clients: dict[int, _Client] = {}
        self.stats = HubStats()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # --- life cycle -----------------------------------------------------------------

    def start(self) -> "LoopbackCanHub":
        """Serve in a daemon thread (tests); `close` stops it."""
        self._thread = threading.Thread(target=self.serve, name="can-hub", daemon=True)
        self._thread.start()
        return self

    def serve(self) -> None:
        """Serve until `close` (or `stop`) is called."""
        while not self._stop.is_set():
            for key, _ in self._selector.select(timeout=_SELECT_TIMEOUT_S):
                if key.data is None:
                    self._accept()
                else:
                    self._read(key.data)

    def stop(self) -> None:
        """Ask `serve` to return (it does within 50 ms)."""
        self._stop.set()

    def close(self) -> None:
        """Stop serving and close every connection (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        for client in list(self._clients.values()):
            self._drop(client)
        try:
            self._selector.unregister(self._server)
        except (KeyError, ValueError):
            pass
        self._server.close()
        self._selector.close()

    def __enter__(self) -> "LoopbackCanHub":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- connections ----------------------------------------------------------------

    def _accept(self) -> None:
        try:
            sock, _ = self._server.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(True)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock)
        self._clients[sock.fileno()] = client
        self._selector.register(sock, selectors.EVENT_READ, client)
        self.stats.clients_seen += 1
        self._write(client, "< hi >")

    def _drop(self, client: _Client) -> None:
        self._clients.pop(client.sock.fileno(), None)
        try:
            self._selector.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()

    def _write(self, client: _Client, text: str) -> bool:
        try:
            client.sock.sendall(text.encode("ascii"))
            return True
        except OSError:
            self._drop(client)
            return False

    def _read(self, client: _Client) -> None:
        try:
            chunk = client.sock.recv(4096)
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(client)
            return
        client.pending += chunk.decode("ascii", errors="replace")
        while (end := client.pending.find(">")) != -1:
            command, client.pending = client.pending[:end + 1], client.pending[end + 1:]
            start = command.find("<")
            if start == -1:
                continue
            try:
                self._handle(client, command[start:])
            except ProtocolError as e:
                self.stats.protocol_errors.append(str(e))
                self._write(client, "< error protocol >")
        if len(client.pending) > MAX_PENDING_CHARS:
            self.stats.protocol_errors.append(f"client sent {len(client.pending)} characters "
                                              "without '>'")
            self._drop(client)

    def _handle(self, client: _Client, command: str) -> None:
        words = command.strip("<> ").split()
        if not client.raw_mode:
            if len(words) == 2 and words[0] == "open":
                client.channel = words[1]
                self._write(client, "< ok >")
            elif words == ["rawmode"] and client.channel is not None:
                client.raw_mode = True
                client.ready_at = time.monotonic() + READY_DELAY_S
                self._write(client, "< ok >")
            else:
                raise ProtocolError(f"expected '< open CHANNEL >' then '< rawmode >', "
                                    f"got {command!r}")
            return
        _, frame = send_to_frame(command, time.time())
        client.frames_in += 1
        self.stats.frames_in += 1
        now = time.monotonic()
        encoded = frame.encode("ascii")
        for other in list(self._clients.values()):
            if other is client or other.channel != client.channel or other.ready_at > now:
                continue
            try:
                other.sock.sendall(encoded)
                self.stats.deliveries += 1
            except OSError:
                self._drop(other)


def main(argv: list[str] | None = None) -> int:
    """Serve until SIGTERM / SIGINT; the first line on stdout is ``port N``."""
    parser = argparse.ArgumentParser(prog="python -m hil.timing.hub", description=__doc__.split("\n")[0])
    parser.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (0: any free)")
    args = parser.parse_args(argv)
    try:
        hub = LoopbackCanHub(args.port)
    except HubError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: hub.stop())
    print(f"port {hub.port}", flush=True)
    try:
        hub.serve()
    finally:
        hub.close()
    print(f"frames in {hub.stats.frames_in}, deliveries {hub.stats.deliveries}, "
          f"clients {hub.stats.clients_seen}, protocol errors {len(hub.stats.protocol_errors)}",
          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
