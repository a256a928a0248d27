import os

import pytest

from sim.autopilot import AutopilotConfig, Orbit, PtyTransport, SimAutopilot, UdpTransport
from sim.flight import VirtualClock, advance
from telemetry.link import CompanionLink, LinkConfig, LinkError, parse_url

T0 = 1_750_000_000_000_000


@pytest.mark.parametrize("url,device,kw", [
    ("/dev/ttyACM0:57600", "/dev/ttyACM0", {"baud": 57600}),
    ("/dev/ttyUSB0", "/dev/ttyUSB0", {"baud": 115200}),
    ("serial:/dev/ttyS1:921600", "/dev/ttyS1", {"baud": 921600}),
    ("udpin:0.0.0.0:14550", "udpin:0.0.0.0:14550", {}),
    ("udpout:192.168.1.10:14550", "udpout:192.168.1.10:14550", {}),
    ("tcp:127.0.0.1:5760", "tcp:127.0.0.1:5760", {}),
    ("flight/telemetry.tlog", "flight/telemetry.tlog", {}),
])
def test_parse_url(url, device, kw):
    assert parse_url(url) == (device, kw)


@pytest.mark.parametrize("bad", ["", "udpin:14550", "http://x", "ttyACM0"])
def test_bad_urls_are_clear_errors(bad):
    with pytest.raises(LinkError):
        parse_url(bad)


def run(link, ap, clock, seconds):
    end = clock() + int(seconds * 1e6)
    while clock() < end:
        advance(ap, link, clock, max(min(ap.next_event_us(), link.next_due_us()), clock()))


@pytest.mark.parametrize("kind", ["pty", "udp"])
def test_companion_announces_requests_and_syncs(kind):
    transport = PtyTransport() if kind == "pty" else UdpTransport()
    clock = VirtualClock(T0)
    got = []
    ap = SimAutopilot(AutopilotConfig(boot_unix_us=T0 - 50_000_000), Orbit(), transport, start_unix_us=T0)
    link = CompanionLink(LinkConfig(transport.url()), on_message=lambda t, raw, msg: got.append((t, msg)),
                         clock=clock)
    link.open()
    try:
        run(link, ap, clock, 3.0)
    finally:
        link.close()
        transport.close()
    assert link.target == (1, 1)
    assert "HEARTBEAT" in ap.received and "TIMESYNC" in ap.received
    assert ap.received.count("COMMAND_LONG") >= 3
    assert link.streams_acked == {"GLOBAL_POSITION_INT", "ATTITUDE", "SYSTEM_TIME"}
    types = {m.get_type() for _, m in got}
    assert {"HEARTBEAT", "GLOBAL_POSITION_INT", "ATTITUDE", "TIMESYNC", "SYSTEM_TIME", "COMMAND_ACK"} <= types
    # receive stamps are the companion clock: 15-45 ms after the send
    ts = [(t, m) for t, m in got if m.get_type() == "TIMESYNC" and m.tc1 > 0]
    assert all(30_000 <= t - m.ts1 // 1000 <= 91_000 for t, m in ts)


def test_fallback_to_request_data_stream():
    transport = PtyTransport()
    clock = VirtualClock(T0)
    ap = SimAutopilot(AutopilotConfig(boot_unix_us=T0 - 1, honour_message_interval=False), Orbit(), transport,
                      start_unix_us=T0)
    link = CompanionLink(LinkConfig(transport.url(), interval_retries=2), clock=clock)
    link.open()
    try:
        run(link, ap, clock, 4.0)
    finally:
        link.close()
        transport.close()
    assert link.stream_fallback
    assert "REQUEST_DATA_STREAM" in ap.received


def test_reconnect_after_a_dropped_link():
    transport = PtyTransport()
    clock = VirtualClock(T0)
    got = []
    ap = SimAutopilot(AutopilotConfig(boot_unix_us=T0 - 1), Orbit(), transport, start_unix_us=T0)
    link = CompanionLink(LinkConfig(transport.url(), reconnect_s=0.5), on_message=lambda *a: got.append(a),
                         clock=clock)
    link.open()
    try:
        run(link, ap, clock, 1.0)
        n_before = len(got)
        # the serial port fails under the reader (as when a USB adapter is pulled): a real I/O error
        os.close(link.conn.port.fd)
        link.poll()
        assert not link.connected
        run(link, ap, clock, 2.0)
    finally:
        link.close()
        transport.close()
    assert link.reconnects == 1 and len(got) > n_before + 10


def test_tlog_playback_keeps_file_times(tmp_path):
    from tests.telemetry.tlogfactory import T0 as F0
    from tests.telemetry.tlogfactory import TlogBuilder, factory_flight

    b = TlogBuilder()
    factory_flight(b, duration_s=1.0)
    p = tmp_path / "x.tlog"
    p.write_bytes(b.data())
    got = []
    link = CompanionLink(LinkConfig(str(p)), on_message=lambda t, raw, msg: got.append((t, raw)))
    link.open()
    while link.connected:
        link.poll()
    assert [raw for _, raw in got] == [raw for _, raw in b.items]
    assert got[0][0] == F0
