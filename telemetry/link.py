"""The companion's MAVLink link: one URL → pymavlink connection, announce, request, log, reconnect.

URLs (anything pymavlink's ``mavlink_connection`` takes, plus a baud suffix for serial devices):

- ``/dev/ttyACM0:57600`` or ``/dev/ttyUSB0`` (115200 baud) or ``serial:/dev/ttyS1:921600``
- ``udpin:0.0.0.0:14550`` (listen), ``udpout:192.168.1.10:14550`` (send first), ``tcp:host:5760``
- ``flight/telemetry.tlog`` (playback; receive times are the file's)

:class:`CompanionLink` (poll-driven, one owner thread; the daemon calls :meth:`poll` in its loop):

- a HEARTBEAT as MAV_TYPE_ONBOARD_CONTROLLER from component 191 every ``heartbeat_s``;
- TIMESYNC requests every ``timesync_s`` (``tc1`` = 0, ``ts1`` = companion ns) and replies to the
  autopilot's own TIMESYNC requests;
- MAV_CMD_SET_MESSAGE_INTERVAL per wanted message until acknowledged; after
  ``interval_retries`` unanswered or refused tries, REQUEST_DATA_STREAM (MAVLink 1 style) instead;
- every received message goes to ``on_message(t_unix_us, raw_bytes, msg)`` (e.g. the tlog writer);
- an I/O error closes the connection and reopens it after ``reconnect_s``; the flight continues.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from telemetry import mavlink as _mavlink

log = logging.getLogger(__name__)

COMPANION_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER

#: message name -> rate (Hz) the pose pipeline wants.
DEFAULT_STREAMS = {"GLOBAL_POSITION_INT": 10.0, "ATTITUDE": 20.0, "SYSTEM_TIME": 1.0}


class LinkError(OSError):
    """A link URL that cannot be opened or parsed."""


def now_unix_us() -> int:
    return time.time_ns() // 1000


def parse_url(url: str) -> tuple[str, dict]:
    """(pymavlink device string, keyword arguments) of a link URL (see the module docstring)."""
    if not url or not isinstance(url, str):
        raise LinkError(f"empty link URL {url!r}")
    u = url.strip()
    if u.startswith("serial:"):
        u = u[len("serial:"):]
    if u.startswith(("udpin:", "udpout:", "udp:", "tcp:", "tcpin:", "udpbcast:")):
        if not re.match(r"^[a-z]+:[^:]*:\d+$", u):
            raise LinkError(f"link URL {url!r}: expected KIND:HOST:PORT")
        return u, {}
    if u.endswith(".tlog") or u.endswith(".mavlink"):
        return u, {}
    m = re.match(r"^(/[^:]+|COM\d+)(?::(\d+))?$", u)
    if m:
        return m.group(1), {"baud": int(m.group(2) or 115200)}
    raise LinkError(f"link URL {url!r}: expected a serial device (/dev/ttyACM0:57600), udpin:/udpout:/tcp:"
                    "HOST:PORT or a .tlog file")


def open_connection(url: str, source_system: int = 1, source_component: int = COMPANION_COMPONENT):
    """A pymavlink connection for ``url`` speaking MAVLink 2 (ardupilotmega dialect)."""
    _mavlink.dialect()
    from pymavlink import mavutil

    device, kwargs = parse_url(url)
    try:
        conn = mavutil.mavlink_connection(device, source_system=source_system,
                                          source_component=source_component, dialect="ardupilotmega",
                                          autoreconnect=False, **kwargs)
    except Exception as exc:  # noqa: BLE001 - pymavlink raises assorted errors (serial, socket)
        raise LinkError(f"cannot open link {url!r}: {exc}") from exc
    if hasattr(conn, "mav") and conn.mav is not None:
        conn.mav.robust_parsing = True
    return conn


@dataclass
class LinkConfig:
    url: str
    source_system: int = 1
    heartbeat_s: float = 1.0
    timesync_s: float = 0.2
    streams: dict = field(default_factory=lambda: dict(DEFAULT_STREAMS))
    #: resend an unacknowledged SET_MESSAGE_INTERVAL after this long (s)
    interval_retry_s: float = 1.0
    interval_retries: int = 3
    reconnect_s: float = 1.0


class CompanionLink:
    """The companion side of one MAVLink link (see the module docstring).

    ``clock``: companion unix µs (``time.time_ns() // 1000`` on hardware, a virtual clock in the simulator).
    ``on_message(t_unix_us, raw, msg)``: called for every received message.
    """

    def __init__(self, config: LinkConfig, on_message: Callable | None = None, clock=now_unix_us) -> None:
        self.config = config
        self.on_message = on_message
        self.clock = clock
        self.conn = None
        self.target: tuple[int, int] | None = None  # autopilot (system, component)
        self.n_received = 0
        self.n_sent = 0
        self.reconnects = 0
        self.streams_acked: set[str] = set()
        self.stream_fallback = False
        self._next_hb = 0
        self._next_ts = 0
        self._interval_tries: dict[str, int] = {}
        self._next_interval = 0
        self._down_since: int | None = None
        self._playback = False

    # ---- connection ----------------------------------------------------------------------------
    def open(self) -> None:
        self.conn = open_connection(self.config.url, self.config.source_system)
        self._playback = parse_url(self.config.url)[0].endswith((".tlog", ".mavlink"))
        self._down_since = None

    def close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            except Exception:  # noqa: BLE001
                pass
        self.conn = None

    def _dropped(self, exc: Exception) -> None:
        log.warning("link %s dropped (%s); reconnecting every %.1f s", self.config.url, exc, self.config.reconnect_s)
        self.close()
        self._down_since = self.clock()

    def _try_reconnect(self) -> bool:
        now = self.clock()
        if self._down_since is not None and now - self._down_since < self.config.reconnect_s * 1e6:
            return False
        try:
            self.open()
        except LinkError as exc:
            log.debug("reconnect failed: %s", exc)
            self._down_since = now
            return False
        self.reconnects += 1
        self.streams_acked.clear()
        self._interval_tries.clear()
        log.info("link %s reconnected", self.config.url)
        return True

    @property
    def connected(self) -> bool:
        return self.conn is not None

    # ---- sending -------------------------------------------------------------------------------
    def _send(self, msg) -> None:
        if self.conn is None or self._playback:
            return
        if getattr(self.conn, "udp_server", False) and not getattr(self.conn, "clients", None):
            return  # udpin: nobody has talked to us yet, so there is no address to answer
        try:
            self.conn.mav.send(msg)
            self.n_sent += 1
        except OSError as exc:
            self._dropped(exc)

    def _tick(self) -> None:
        now = self.clock()
        m = _mavlink.dialect()
        if now >= self._next_hb:
            self._send(m.MAVLink_heartbeat_message(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID,
                                                   0, 0, m.MAV_STATE_ACTIVE, 3))
            self._next_hb = now + int(self.config.heartbeat_s * 1e6)
        if self.target is None:
            return
        if now >= self._next_ts:
            self._send(m.MAVLink_timesync_message(0, now * 1000))
            self._next_ts = now + int(self.config.timesync_s * 1e6)
        if now >= self._next_interval and not self.stream_fallback:
            missing = [s for s in self.config.streams if s not in self.streams_acked]
            for name in missing:
                tries = self._interval_tries.get(name, 0)
                if tries >= self.config.interval_retries:
                    self._fallback_streams()
                    break
                self._interval_tries[name] = tries + 1
                msg_id = getattr(m, f"MAVLINK_MSG_ID_{name}")
                interval_us = 1e6 / self.config.streams[name]
                self._send(m.MAVLink_command_long_message(self.target[0], self.target[1],
                                                          m.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                          msg_id, interval_us, 0, 0, 0, 0, 0))
            self._next_interval = now + int(self.config.interval_retry_s * 1e6)

    def _fallback_streams(self) -> None:
        m = _mavlink.dialect()
        log.warning("autopilot does not honour SET_MESSAGE_INTERVAL; falling back to REQUEST_DATA_STREAM")
        self.stream_fallback = True
        for stream, rate in ((m.MAV_DATA_STREAM_POSITION, 10), (m.MAV_DATA_STREAM_EXTRA1, 20),
                             (m.MAV_DATA_STREAM_EXTENDED_STATUS, 2)):
            self._send(m.MAVLink_request_data_stream_message(self.target[0], self.target[1], stream, rate, 1))

    def next_due_us(self) -> int:
        """Companion time (unix µs) at which :meth:`poll` next has something to send."""
        if self.conn is None:
            return (self._down_since or self.clock()) + int(self.config.reconnect_s * 1e6)
        due = [self._next_hb]
        if self.target is not None:
            due.append(self._next_ts)
            if not self.stream_fallback and len(self.streams_acked) < len(self.config.streams):
                due.append(self._next_interval)
        return min(due)

    # ---- receiving -----------------------------------------------------------------------------
    def poll(self, max_messages: int = 10_000, wait_s: float = 0.0, expect: int = 0) -> int:
        """Send what is due, then read what is available (up to ``max_messages``); messages read.

        ``expect``: keep reading (up to ``wait_s`` seconds of real time) until that many arrived.
        """
        if self.conn is None and not self._try_reconnect():
            return 0
        self._tick()
        n = 0
        deadline = time.monotonic() + wait_s
        while n < max_messages and self.conn is not None:
            try:
                msg = self.conn.recv_msg()
            except OSError as exc:
                self._dropped(exc)
                break
            except Exception as exc:  # noqa: BLE001 - pyserial raises SerialException (an IOError) or others
                self._dropped(exc)
                break
            if msg is None:
                if n < expect and time.monotonic() < deadline:
                    time.sleep(0.0002)
                    continue
                if self._playback:
                    self.close()
                break
            if msg.get_type() == "BAD_DATA":
                continue
            n += 1
            self._handle(msg)
        return n

    def _handle(self, msg) -> None:
        t_us = int(msg._timestamp * 1e6) if self._playback else self.clock()
        raw = bytes(msg.get_msgbuf())
        self.n_received += 1
        if self.on_message is not None:
            self.on_message(t_us, raw, msg)
        typ = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        m = _mavlink.dialect()
        if self.target is None and _mavlink.is_autopilot_heartbeat(msg):
            self.target = src
            log.info("autopilot found: system %d component %d", *src)
        elif typ == "TIMESYNC" and msg.tc1 == 0 and src == self.target:
            self._send(m.MAVLink_timesync_message(self.clock() * 1000, msg.ts1))
        elif typ == "COMMAND_ACK" and msg.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            if msg.result == m.MAV_RESULT_ACCEPTED:
                # Acks do not say which message; credit the oldest request still open.
                for name in self.config.streams:
                    if name not in self.streams_acked:
                        self.streams_acked.add(name)
                        break
            else:
                for name in self.config.streams:
                    self._interval_tries[name] = self.config.interval_retries
