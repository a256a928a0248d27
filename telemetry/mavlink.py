"""MAVLink dialect access and the tlog format: write, and read robustly.

A tlog is what every ground tool reads: per message, an 8-byte big-endian unix timestamp (µs,
the receiver's clock) followed by the raw MAVLink frame (v1 magic 0xFE or v2 magic 0xFD).

:func:`dialect` returns pymavlink's MAVLink 2 ``ardupilotmega`` module; it sets ``MAVLINK20`` before
the first pymavlink import, so import pymavlink through this module (or set it yourself first).

:func:`read_tlog` never raises on content: random bytes, bad CRCs and unknown message ids are
skipped and counted, a truncated last record is reported, and the parser resynchronises on the
next plausible (timestamp, magic) pair.
"""

from __future__ import annotations

import logging
import os
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")

log = logging.getLogger(__name__)

MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD
#: Plausible tlog timestamps: 2000-01-01 .. 2100-01-01 in unix µs.
_T_MIN_US = 946_684_800_000_000
_T_MAX_US = 4_102_444_800_000_000


#: HEARTBEAT types that are not a vehicle: GCS, onboard controller, gimbal, ADSB, camera, ...
NOT_VEHICLE_TYPES = frozenset({6, 18, 26, 27, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39, 40, 41, 42})
MAV_AUTOPILOT_INVALID = 8


def is_autopilot_heartbeat(msg) -> bool:
    """True for the HEARTBEAT of a vehicle's autopilot (not a GCS, companion, gimbal, camera...)."""
    return (msg.get_type() == "HEARTBEAT" and msg.autopilot != MAV_AUTOPILOT_INVALID
            and msg.type not in NOT_VEHICLE_TYPES)


def dialect():
    """pymavlink's MAVLink 2 ``ardupilotmega`` dialect module."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


def new_parser(source_system: int = 255, source_component: int = 0):
    """A fresh ``MAVLink`` encoder/decoder of the dialect (no file attached)."""
    m = dialect()
    mav = m.MAVLink(None, srcSystem=source_system, srcComponent=source_component)
    mav.robust_parsing = True
    return mav


def frame_length(buf: bytes | bytearray | memoryview, pos: int) -> int | None:
    """Length of the MAVLink frame starting at ``buf[pos]`` or None when it is not a magic byte.

    Returns the full length (header, payload, CRC, signature); the caller checks it fits.
    """
    if pos + 2 > len(buf):
        return None
    magic = buf[pos]
    n = buf[pos + 1]
    if magic == MAGIC_V1:
        return 6 + n + 2
    if magic == MAGIC_V2:
        if pos + 3 > len(buf):
            return None
        signed = buf[pos + 2] & 0x01
        return 10 + n + 2 + (13 if signed else 0)
    return None


@dataclass
class TlogRecord:
    """One message of a tlog: receive time (unix µs, the logger's clock), decoded message, raw bytes."""

    t_unix_us: int
    msg: object
    raw: bytes

    @property
    def type(self) -> str:
        return self.msg.get_type()


@dataclass
class TlogReadResult:
    """Everything :func:`read_tlog` found, including the problems, one line each."""

    records: list[TlogRecord]
    bytes_total: int = 0
    bytes_skipped: int = 0
    bad_crc: int = 0
    unknown_ids: Counter = field(default_factory=Counter)
    truncated_tail: bool = False
    problems: list[str] = field(default_factory=list)


def _plausible_ts(buf, pos: int) -> bool:
    if pos + 9 > len(buf):
        return False
    t = struct.unpack_from(">Q", buf, pos)[0]
    return _T_MIN_US <= t <= _T_MAX_US and buf[pos + 8] in (MAGIC_V1, MAGIC_V2)


def parse_tlog_bytes(data: bytes, name: str = "tlog") -> TlogReadResult:
    """Parse tlog bytes (see module docstring). Never raises on content."""
    m = dialect()
    mav = new_parser()
    res = TlogReadResult(records=[], bytes_total=len(data))
    buf = memoryview(data)
    pos, n = 0, len(data)
    unpack_ts = struct.Struct(">Q").unpack_from
    while pos < n:
        if n - pos < 11:  # not even a timestamp and a frame header
            res.truncated_tail = True
            res.problems.append(f"{name}: truncated last record ({n - pos} bytes at offset {pos})")
            break
        t = unpack_ts(buf, pos)[0]
        flen = frame_length(buf, pos + 8)
        if not (_T_MIN_US <= t <= _T_MAX_US) or flen is None:
            nxt = _resync(data, pos + 1)
            res.bytes_skipped += nxt - pos
            pos = nxt
            continue
        end = pos + 8 + flen
        if end > n:
            # Either the file ends mid-record or junk here only looks like an over-long frame:
            # a readable record further on means the latter, so skip to it instead of stopping.
            nxt = _resync(data, pos + 1)
            if nxt < n:
                res.bytes_skipped += nxt - pos
                pos = nxt
                continue
            res.truncated_tail = True
            res.problems.append(f"{name}: truncated last record ({n - pos} of {8 + flen} bytes at offset {pos})")
            break
        raw = bytes(buf[pos + 8:end])
        try:
            msg = mav.decode(bytearray(raw))
        except m.MAVError as exc:
            text = str(exc)
            if ("unknown MAVLink message ID" in text or "Unknown MAVLink message ID" in text) and (
                    _unknown_frame_is_whole(data, pos, end)):
                msgid = raw[5] if raw[0] == MAGIC_V1 else int.from_bytes(raw[7:10], "little")
                res.unknown_ids[msgid] += 1
                pos = end
                continue
            res.bad_crc += 1
            nxt = _resync(data, pos + 1)
            res.bytes_skipped += nxt - pos
            pos = nxt
            continue
        except Exception:  # noqa: BLE001 - pymavlink raises assorted errors on garbage
            res.bad_crc += 1
            nxt = _resync(data, pos + 1)
            res.bytes_skipped += nxt - pos
            pos = nxt
            continue
        typ = msg.get_type()
        if typ.startswith("UNKNOWN_"):  # a message this dialect does not define (its CRC cannot be checked)
            if _unknown_frame_is_whole(data, pos, end):
                res.unknown_ids[int(typ[8:])] += 1
                pos = end
            else:  # no record follows: this was garbage that looked like a frame
                nxt = _resync(data, pos + 1)
                res.bytes_skipped += nxt - pos
                pos = nxt
            continue
        if typ == "BAD_DATA":
            res.bad_crc += 1
            pos = end
            continue
        res.records.append(TlogRecord(int(t), msg, raw))
        pos = end
    if res.bytes_skipped:
        res.problems.append(f"{name}: skipped {res.bytes_skipped} unreadable bytes")
    if res.bad_crc:
        res.problems.append(f"{name}: {res.bad_crc} frames with a bad CRC or layout skipped")
    if res.unknown_ids:
        ids = ", ".join(f"{k}x{v}" for k, v in sorted(res.unknown_ids.items()))
        res.problems.append(f"{name}: messages of unknown type skipped (id x count: {ids})")
    return res


def _unknown_frame_is_whole(b: bytes, pos: int, end: int) -> bool:
    """Whether the record at ``pos`` whose frame has an unknown id (CRC not checkable) and ends at ``end`` is real.

    Real when a record (or the end of the file) follows it and no record starts inside it; junk that
    happens to read as a long frame swallows the records it covers, so those make it garbage.
    """
    followed = end == len(b) or _plausible_ts(b, end)
    return followed and _resync(b, pos + 1) >= end


def _resync(b: bytes, start: int) -> int:
    """Next offset >= start holding a plausible timestamp followed by a magic byte (or the end)."""
    n = len(b)
    pos = start
    while pos < n:
        i1 = b.find(b"\xfd", pos + 8)
        i2 = b.find(b"\xfe", pos + 8)
        cands = [i for i in (i1, i2) if i >= 0]
        if not cands:
            return n
        i = min(cands)
        if _plausible_ts(b, i - 8):
            return i - 8
        pos = i - 7
    return n


def read_tlog(path: str | Path) -> TlogReadResult:
    """Read a tlog file. Raises ``FileNotFoundError`` when missing; content problems are reported."""
    path = Path(path)
    data = path.read_bytes()
    res = parse_tlog_bytes(data, name=str(path))
    for p in res.problems:
        log.warning("%s", p)
    return res


def tlog_record(t_unix_us: int, raw: bytes) -> bytes:
    """The bytes of one tlog record."""
    return struct.pack(">Q", int(t_unix_us)) + bytes(raw)
