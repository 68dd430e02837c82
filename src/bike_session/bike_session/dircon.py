"""Wahoo Direct Connect (DIRCON, mDNS service ``_wahoo-fitness-tnp._tcp``, TCP port 36866):
BLE GATT carried over TCP, the way Zwift, FulGaz, Wahoo SYSTM, Rouvy and others reach a
trainer on the network. No sockets and no ROS here: :class:`DirconConnection` turns the bytes
an app sent into the bytes to send back, for a table of characteristics
(:class:`Characteristic`); bike_session.ftms_node owns the sockets.

Message (every field big endian except the characteristic values, which are BLE's little
endian): version (1), message type, sequence number (a response echoes the request's),
response code, data length (uint16), data. UUIDs are 128-bit, the 16-bit SIG numbers inside
the Bluetooth base UUID 0000xxxx-0000-1000-8000-00805F9B34FB, sent in that written order.

| type | request data | response data |
|---|---|---|
| 1 discover services | - | service UUIDs |
| 2 discover characteristics | service UUID | service UUID, then per characteristic UUID + properties (1 read, 2 write, 4 notify) |
| 3 read | characteristic UUID | UUID + value |
| 4 write | UUID + value | UUID |
| 5 enable notifications | UUID + 0 / 1 | UUID |
| 6 notification (server to app, sequence 0) | - | UUID + value |

Response codes: 0 success, 1 unknown message type, 2 generic error, 3 service not found,
4 characteristic not found, 5 operation not supported, 6 write failed. A request the table
cannot serve gets its code and the connection stays up. A stream that cannot be framed any
more (another version, a length beyond :data:`MAX_DATA_BYTES`) raises :class:`DirconError`:
the caller says why and closes that connection, and only that one.
(Reference: the unofficial specification at github.com/elfrances/wahoo-fitness-tnp.)
"""
from __future__ import annotations

import dataclasses
import struct
from typing import Callable

VERSION = 1
MSG_DISCOVER_SERVICES = 1
MSG_DISCOVER_CHARACTERISTICS = 2
MSG_READ = 3
MSG_WRITE = 4
MSG_ENABLE_NOTIFICATIONS = 5
MSG_NOTIFICATION = 6

RESP_SUCCESS = 0
RESP_UNKNOWN_TYPE = 1
RESP_GENERIC_ERROR = 2
RESP_SERVICE_NOT_FOUND = 3
RESP_CHARACTERISTIC_NOT_FOUND = 4
RESP_NOT_SUPPORTED = 5
RESP_WRITE_FAILED = 6

PROP_READ = 0x01
PROP_WRITE = 0x02
PROP_NOTIFY = 0x04

DEFAULT_PORT = 36866
MDNS_SERVICE = "_wahoo-fitness-tnp._tcp.local."
# DNS message fields (RFC 1035 s. 4.1): a standard query, a PTR question of class IN (QM: its
# top bit clear, so the answer is multicast)
DNS_FLAGS_QUERY, DNS_TYPE_PTR, DNS_CLASS_IN = 0x0000, 12, 1
HEADER = struct.Struct(">BBBBH")
MAX_DATA_BYTES = 512          # a GATT value is at most 512 bytes; more is not a DIRCON stream
_BASE_TAIL = bytes.fromhex("00001000800000805f9b34fb")


class DirconError(ValueError):
    """A byte stream that is not DIRCON: the connection cannot go on."""


def uuid128(short: int) -> bytes:
    """The 128-bit form of a 16-bit SIG UUID, in DIRCON's byte order."""
    return struct.pack(">I", short) + _BASE_TAIL


def uuid_text(raw: bytes) -> str:
    """0x2ad9 for a SIG UUID, else the 32 hex digits."""
    if len(raw) == 16 and raw[4:] == _BASE_TAIL and raw[:2] == b"\0\0":
        return f"0x{struct.unpack('>I', raw[:4])[0]:04x}"
    return raw.hex()


def encode(msg_type: int, seq: int, data: bytes = b"", code: int = RESP_SUCCESS) -> bytes:
    return HEADER.pack(VERSION, msg_type, seq & 0xFF, code, len(data)) + data


@dataclasses.dataclass
class Message:
    msg_type: int
    seq: int
    code: int
    data: bytes


def split_messages(buffer: bytearray) -> list[Message]:
    """Take every whole message off the front of ``buffer`` (a partial one stays)."""
    out = []
    while len(buffer) >= HEADER.size:
        version, msg_type, seq, code, length = HEADER.unpack_from(buffer)
        if version != VERSION:
            raise DirconError(f"protocol version {version} (expected {VERSION}); first bytes {bytes(buffer[:8]).hex()}")
        if length > MAX_DATA_BYTES:
            raise DirconError(f"message of {length} data bytes (at most {MAX_DATA_BYTES})")
        if len(buffer) < HEADER.size + length:
            break
        out.append(Message(msg_type, seq, code, bytes(buffer[HEADER.size:HEADER.size + length])))
        del buffer[:HEADER.size + length]
    return out


@dataclasses.dataclass
class Characteristic:
    uuid: int
    properties: int
    read: Callable[[], bytes] | None = None
    # write(value, client): the notifications it causes, [(characteristic uuid, value), ...];
    # client: the DirconConnection that wrote (FTMS control is an app's, not everyone's)
    write: Callable[[bytes, DirconConnection], list] | None = None


class DirconConnection:
    """One app's connection: the requests it sent, its notification subscriptions."""

    def __init__(self, services: dict[int, list[Characteristic]]):
        self.services = services
        self.by_uuid = {uuid128(c.uuid): c for chars in services.values() for c in chars}
        self.buffer = bytearray()
        self.subscribed: set[int] = set()
        self.log: list[str] = []            # refusals, for the owner to log (then cleared)

    def feed(self, data: bytes) -> bytes:
        """Bytes received -> bytes to send (responses, and the notifications a write
        caused for characteristics this connection subscribed to). DirconError: close."""
        self.buffer += data
        out = bytearray()
        for msg in split_messages(self.buffer):
            out += self._handle(msg)
        return bytes(out)

    def notification(self, uuid: int, value: bytes) -> bytes:
        """A notification of ``uuid`` for this connection, b"" when it did not subscribe."""
        return encode(MSG_NOTIFICATION, 0, uuid128(uuid) + value) if uuid in self.subscribed else b""

    def _refuse(self, msg: Message, code: int, why: str, data: bytes = b"") -> bytes:
        self.log.append(f"DIRCON request type {msg.msg_type} (seq {msg.seq}) refused: {why}")
        return encode(msg.msg_type, msg.seq, data, code)

    def _handle(self, msg: Message) -> bytes:
        if msg.msg_type == MSG_DISCOVER_SERVICES:
            return encode(msg.msg_type, msg.seq, b"".join(uuid128(s) for s in self.services))
        if msg.msg_type not in (MSG_DISCOVER_CHARACTERISTICS, MSG_READ, MSG_WRITE, MSG_ENABLE_NOTIFICATIONS):
            return self._refuse(msg, RESP_UNKNOWN_TYPE, "unknown message type")
        if len(msg.data) < 16:
            return self._refuse(msg, RESP_GENERIC_ERROR, f"{len(msg.data)} data bytes, a UUID needs 16")
        uuid, rest = msg.data[:16], msg.data[16:]
        if msg.msg_type == MSG_DISCOVER_CHARACTERISTICS:
            for service, chars in self.services.items():
                if uuid128(service) == uuid:
                    return encode(msg.msg_type, msg.seq, uuid + b"".join(uuid128(c.uuid) + bytes([c.properties])
                                                                         for c in chars))
            return self._refuse(msg, RESP_SERVICE_NOT_FOUND, f"no service {uuid_text(uuid)}", uuid)
        char = self.by_uuid.get(uuid)
        if char is None:
            return self._refuse(msg, RESP_CHARACTERISTIC_NOT_FOUND, f"no characteristic {uuid_text(uuid)}", uuid)
        if msg.msg_type == MSG_READ:
            if not char.properties & PROP_READ or char.read is None:
                return self._refuse(msg, RESP_NOT_SUPPORTED, f"{uuid_text(uuid)} cannot be read", uuid)
            return encode(msg.msg_type, msg.seq, uuid + char.read())
        if msg.msg_type == MSG_ENABLE_NOTIFICATIONS:
            if not char.properties & PROP_NOTIFY:
                return self._refuse(msg, RESP_NOT_SUPPORTED, f"{uuid_text(uuid)} does not notify", uuid)
            if len(rest) != 1 or rest[0] not in (0, 1):
                return self._refuse(msg, RESP_GENERIC_ERROR, f"enable flag {rest.hex() or 'missing'} (0 or 1)", uuid)
            (self.subscribed.add if rest[0] else self.subscribed.discard)(char.uuid)
            return encode(msg.msg_type, msg.seq, uuid)
        # write
        if not char.properties & PROP_WRITE or char.write is None:
            return self._refuse(msg, RESP_NOT_SUPPORTED, f"{uuid_text(uuid)} cannot be written", uuid)
        caused = char.write(rest, self)
        return encode(msg.msg_type, msg.seq, uuid) + b"".join(self.notification(u, v) for u, v in caused)


MAX_OUTBOX_BYTES = 1 << 16     # an app that does not read this much is dropped, not waited for


class DirconServer:
    """A non-blocking TCP server of :class:`DirconConnection` s, driven by :meth:`poll` (the
    node calls it from a timer: no thread of its own). ``log(text, warning)`` gets every
    connection change and refusal; ``on_close(connection)`` is called when an app's connection
    is gone (whatever closed it)."""

    def __init__(self, host: str, port: int, services: dict[int, list[Characteristic]],
                 log: Callable[[str, bool], None], on_close: Callable[[DirconConnection], None] | None = None):
        import selectors
        import socket

        self._socket_mod = socket
        self.services = services
        self.log = log
        self.on_close = on_close
        self.sel = selectors.DefaultSelector()
        self.listener = socket.create_server((host, port), reuse_port=False, backlog=4)
        self.listener.setblocking(False)
        self.sel.register(self.listener, selectors.EVENT_READ, None)
        self.conns: dict = {}           # socket -> [DirconConnection, outbox bytearray, peer text]
        self.host, self.port = self.listener.getsockname()[:2]

    def poll(self, timeout_s: float = 0.0) -> None:
        for key, _events in self.sel.select(timeout_s):
            if key.data is None:
                self._accept()
            else:
                self._read(key.fileobj)
        for sock in list(self.conns):
            self._flush(sock)

    def broadcast(self, uuid: int, value: bytes) -> None:
        """Notify ``uuid`` to every connection that subscribed to it."""
        for sock, (conn, outbox, _peer) in list(self.conns.items()):
            outbox += conn.notification(uuid, value)

    def _accept(self) -> None:
        import selectors
        try:
            sock, addr = self.listener.accept()
        except OSError:
            return
        sock.setblocking(False)
        # DIRCON is latency-sensitive (a control point response): no Nagle delay
        sock.setsockopt(self._socket_mod.IPPROTO_TCP, self._socket_mod.TCP_NODELAY, 1)
        sock.setsockopt(self._socket_mod.SOL_SOCKET, self._socket_mod.SO_KEEPALIVE, 1)
        # a small kernel buffer: an app that stopped reading shows in the outbox within seconds
        # instead of megabytes of stale telemetry piling up unseen
        sock.setsockopt(self._socket_mod.SOL_SOCKET, self._socket_mod.SO_SNDBUF, 16384)
        peer = f"{addr[0]}:{addr[1]}"
        self.conns[sock] = [DirconConnection(self.services), bytearray(), peer]
        self.sel.register(sock, selectors.EVENT_READ, peer)
        self.log(f"app connected from {peer}", False)

    def _read(self, sock) -> None:
        entry = self.conns.get(sock)
        if entry is None:
            return
        conn, outbox, peer = entry
        try:
            data = sock.recv(4096)
        except BlockingIOError:
            return
        except ConnectionResetError:
            self._close(sock, f"app {peer} disconnected (connection reset)", False)
            return
        except OSError as exc:
            self._close(sock, f"app {peer}: {exc}", True)
            return
        if not data:
            self._close(sock, f"app {peer} disconnected", False)
            return
        try:
            outbox += conn.feed(data)
        except DirconError as exc:
            self._close(sock, f"app {peer}: not a DIRCON stream ({exc}); connection closed", True)
            return
        except Exception as exc:  # noqa: BLE001 - a fault serving one app must not stop the bike
            self._close(sock, f"app {peer}: internal error serving a request ({type(exc).__name__}: {exc}); "
                              "connection closed", True)
            return
        for text in conn.log:
            self.log(f"app {peer}: {text}", True)
        conn.log.clear()

    def _flush(self, sock) -> None:
        entry = self.conns.get(sock)
        if entry is None or not entry[1]:
            return
        outbox = entry[1]
        try:
            sent = sock.send(bytes(outbox))     # a copy: the outbox may grow meanwhile
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            self._close(sock, f"app {entry[2]}: {exc}", True)
            return
        del outbox[:sent]
        if len(outbox) > MAX_OUTBOX_BYTES:
            self._close(sock, f"app {entry[2]} reads nothing ({len(outbox)} bytes waiting): connection closed", True)

    def _close(self, sock, why: str, warning: bool) -> None:
        self.log(why, warning)          # said before the app sees the close
        entry = self.conns.pop(sock, None)
        if entry is not None and self.on_close is not None:
            self.on_close(entry[0])
        try:
            self.sel.unregister(sock)
        except (KeyError, ValueError):
            pass
        sock.close()

    def close(self) -> None:
        for sock in list(self.conns):
            self._close(sock, f"app {self.conns[sock][2]}: server stopping", False)
        self.sel.unregister(self.listener)
        self.listener.close()
        self.sel.close()


class Advertiser:
    """The mDNS record apps look for (python-zeroconf): ``<name>._wahoo-fitness-tnp._tcp.local.``
    at ``address``:``port`` with the TXT keys a DIRCON trainer sends (ble-service-uuids,
    mac-address, serial-number). Registration probes the network for about 2 s, so it runs in
    a thread of its own; when ``done`` is set, ``error`` is None or the error text and
    ``advertised_name`` the name registered (``name``, or ``name-2``, ... if that was taken)."""

    def __init__(self, name: str, addresses: list[str], port: int, serial: str, log: Callable[[str, bool], None]):
        import threading
        self.name, self.addresses, self.port, self.serial, self.log = name, addresses, port, serial, log
        self.zc = self.info = None
        self.done = threading.Event()
        self.error: str | None = None
        self.advertised_name: str | None = None
        self.thread = threading.Thread(target=self._register, name="mdns", daemon=True)
        self.thread.start()

    def _register(self) -> None:
        import socket
        try:
            from zeroconf import IPVersion, ServiceInfo, Zeroconf
            self.zc = Zeroconf(interfaces=self.addresses, ip_version=IPVersion.V4Only)
            self.info = ServiceInfo(
                MDNS_SERVICE, f"{self.name}.{MDNS_SERVICE}", port=self.port,
                server=f"bike-{local_mac(self.serial).replace('-', '').lower()}.local.",
                addresses=[socket.inet_aton(a) for a in self.addresses],
                properties={"ble-service-uuids": "0x1826,0x1818", "serial-number": self.serial,
                            "mac-address": local_mac(self.serial)})
            # the type's 17-byte name is longer than RFC 6335's 15: DIRCON's own, not ours to fix.
            # A name another bike on the network holds (two testbeds, one namespace) becomes
            # "<name>-2", ... as mDNS does it: both stay findable, this one under the name logged
            self._ask_for_namesakes()
            self.zc.register_service(self.info, allow_name_change=True, strict=False)
            self.advertised_name = self.info.name[:-len("." + MDNS_SERVICE)]
            taken = "" if self.advertised_name == self.name else f"; {self.name!r} is taken on this network"
            self.log(f"advertised as {self.advertised_name!r} ({MDNS_SERVICE} on {', '.join(self.addresses)}){taken}",
                     bool(taken))
        except Exception as exc:  # noqa: BLE001 - no advert is a warning, the server still serves
            self.error = f"{type(exc).__name__}: {exc}"
            self.log(f"mDNS advertisement failed ({self.error}); apps must be given the address", True)
        finally:
            self.done.set()

    def _ask_for_namesakes(self) -> None:
        """One multicast (QM) question for the service type's instances, sent before the probes:
        its answers reach every socket on port 5353, so one a bike on this host holds lands in
        the cache during the probing (about 1 s) and the name is changed. The probes are QU
        (RFC 6762 s. 8.1) and a unicast answer to port 5353 reaches only one of the sockets a
        host shares it by: without this, two bikes of one name on one host both held it."""
        from zeroconf import DNSOutgoing, DNSQuestion
        out = DNSOutgoing(DNS_FLAGS_QUERY)
        out.add_question(DNSQuestion(MDNS_SERVICE, DNS_TYPE_PTR, DNS_CLASS_IN))
        self.zc.send(out)

    def close(self) -> None:
        self.done.wait(5)
        if self.zc is not None:
            try:
                if self.info is not None and self.error is None:
                    self.zc.unregister_service(self.info)
            finally:
                self.zc.close()


def local_mac(serial: str) -> str:
    """A locally administered MAC address (first byte 0x02) for the TXT record, fixed for a
    serial number: apps tell trainers apart by it, so two bikes on one network must differ."""
    import hashlib
    tail = hashlib.sha1(serial.encode()).digest()[:5]
    return "-".join(f"{b:02X}" for b in (0x02, *tail))


def host_addresses(host: str) -> list[str]:
    """The IPv4 addresses to advertise for a server bound to ``host``: itself, or for 0.0.0.0
    every address of this host but loopback's (ifaddr, which python-zeroconf brings)."""
    if host not in ("0.0.0.0", ""):
        return [host]
    import ifaddr
    found = [ip.ip for adapter in ifaddr.get_adapters() for ip in adapter.ips
             if isinstance(ip.ip, str) and not ip.ip.startswith("127.")]
    return found or ["127.0.0.1"]


class DirconClient:
    """The app's end, blocking (tests, and ``./bike trainer``, a quick look at a trainer):
    requests answered in order; notifications that arrive meanwhile are kept in
    :attr:`notifications` as (uuid, value)."""

    def __init__(self, host: str, port: int, timeout_s: float = 5.0):
        import socket
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        import collections
        self.buffer = bytearray()
        self.pending: collections.deque = collections.deque()
        self.seq = 0
        self.notifications: list[tuple[int, bytes]] = []

    def _next(self) -> Message:
        while not self.pending:
            data = self.sock.recv(4096)
            if not data:
                raise ConnectionError("the bike closed the connection")
            self.buffer += data
            self.pending.extend(split_messages(self.buffer))
        return self.pending.popleft()

    def _keep(self, msg: Message) -> None:
        uuid = struct.unpack(">I", msg.data[:4])[0] if len(msg.data) >= 16 else -1
        self.notifications.append((uuid, msg.data[16:]))

    def request(self, msg_type: int, data: bytes = b"") -> Message:
        self.seq = (self.seq + 1) & 0xFF
        self.sock.sendall(encode(msg_type, self.seq, data))
        while True:
            msg = self._next()
            if msg.msg_type == MSG_NOTIFICATION:
                self._keep(msg)
                continue
            return msg

    def wait_notification(self, uuid: int, timeout_s: float = 5.0) -> bytes:
        """The first kept or arriving notification of ``uuid`` (taken off the list)."""
        import time
        end = time.monotonic() + timeout_s
        while True:
            for i, (u, value) in enumerate(self.notifications):
                if u == uuid:
                    del self.notifications[i]
                    return value
            left = end - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no notification of 0x{uuid:04x} in {timeout_s:g} s")
            self.sock.settimeout(left)
            try:
                msg = self._next()
            finally:
                self.sock.settimeout(None)
            if msg.msg_type == MSG_NOTIFICATION:
                self._keep(msg)

    def take_notifications(self, uuid: int) -> list[bytes]:
        """The notifications of ``uuid`` kept so far (taken off the list; no wait)."""
        taken = [value for u, value in self.notifications if u == uuid]
        self.notifications = [(u, value) for u, value in self.notifications if u != uuid]
        return taken

    def read(self, uuid: int) -> bytes:
        msg = self.request(MSG_READ, uuid128(uuid))
        if msg.code != RESP_SUCCESS:
            raise ValueError(f"read of 0x{uuid:04x}: response code {msg.code}")
        return msg.data[16:]

    def write(self, uuid: int, value: bytes) -> Message:
        return self.request(MSG_WRITE, uuid128(uuid) + value)

    def subscribe(self, uuid: int) -> Message:
        return self.request(MSG_ENABLE_NOTIFICATIONS, uuid128(uuid) + b"\x01")

    def close(self) -> None:
        self.sock.close()
