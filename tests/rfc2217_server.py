"""A real RFC 2217 serial server for tests: pyserial's ``serial.rfc2217.PortManager``
bridging a TCP socket on loopback to a serial port (a simulator's pty), as ser2net or an
ESP-link does to a UART. The client's baud rate, framing and modem lines are negotiated
onto the pty (so the simulator answers only at its line's speed, as on a wire)::

    with simulated_bus(["huiwen-aq@3"], baudrate=9600) as sim, Rfc2217Server(sim.port) as url:
        rtupoll("read", "-p", url, "huiwen-aq@3", "co2")   # url: rfc2217://127.0.0.1:PORT

One client at a time, one after another (a one-shot command connects, reads, leaves);
each connection opens the serial port afresh and closes it when the client goes.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from types import TracebackType

import serial
import serial.rfc2217


class _PtyPort(serial.Serial):  # type: ignore[misc]
    """A pty as the server's serial port: it has no modem lines (their ioctls fail on it),
    so it reports them all low, as an idle UART's would be, and takes DTR and RTS as
    pyserial's own open does on a pty (PortManager sets and asks for them)."""

    cts = dsr = ri = cd = property(lambda self: False)

    def _update_dtr_state(self) -> None:
        with contextlib.suppress(OSError):
            super()._update_dtr_state()

    def _update_rts_state(self) -> None:
        with contextlib.suppress(OSError):
            super()._update_rts_state()


class _Connection:
    """What ``PortManager`` writes to: the client's socket (its replies to negotiation,
    modem-state notifications), thread-safe."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock, self._lock = sock, threading.Lock()

    def write(self, data: bytes) -> None:
        with self._lock, contextlib.suppress(OSError):
            self.sock.sendall(data)


class Rfc2217Server:
    def __init__(self, device: str) -> None:
        self.device = device
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"rfc2217://127.0.0.1:{self._listener.getsockname()[1]}"
        self.connections = 0  # clients served so far
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="rfc2217-server",
                                        daemon=True)

    def __enter__(self) -> str:
        self._thread.start()
        return self.url

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        self._listener.close()
        self._thread.join(10)

    def _serve(self) -> None:
        self._listener.settimeout(0.1)
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed
            with client:
                self.connections += 1
                self._bridge(client)

    def _bridge(self, client: socket.socket) -> None:
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        port = _PtyPort()
        port.port = self.device
        port.timeout = 0.05
        port.dtr = port.rts = False
        port.open()
        manager = serial.rfc2217.PortManager(port, _Connection(client))
        done = threading.Event()

        def to_client() -> None:  # the serial port's bytes, escaped, to the network
            while not done.is_set():
                try:
                    data = port.read(port.in_waiting or 1)
                except (serial.SerialException, OSError, TypeError):
                    break  # (closed under us)
                if data:
                    manager.connection.write(b"".join(manager.escape(data)))
                with contextlib.suppress(Exception):
                    manager.check_modem_lines()

        reader = threading.Thread(target=to_client, name="rfc2217-to-client", daemon=True)
        reader.start()
        client.settimeout(0.1)
        try:
            while not self._stop.is_set():
                try:
                    data = client.recv(1024)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not data:
                    break  # the client left
                port.write(b"".join(manager.filter(data)))  # negotiation taken out
        finally:
            done.set()
            reader.join(5)
            port.close()
