"""The notify protocol over a real unix datagram socket."""

import os
import socket

from agent.sdnotify import Notifier, watchdog_interval_s


def test_messages_arrive_as_systemd_reads_them(tmp_path):
    path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(path)
    server.settimeout(2)
    n = Notifier(path)
    assert n.enabled
    assert n.ready("capturing")
    assert server.recv(4096) == b"READY=1\nSTATUS=capturing"
    assert n.status("two\nlines")
    assert server.recv(4096) == b"STATUS=two lines"
    assert n.watchdog() and server.recv(4096) == b"WATCHDOG=1"
    n.close()
    server.close()


def test_noop_outside_systemd_and_on_a_dead_socket(tmp_path, monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not Notifier().enabled and not Notifier().ready()
    assert Notifier(str(tmp_path / "missing.sock")).watchdog() is False


def test_watchdog_interval(monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "20000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert watchdog_interval_s() == 10.0
    monkeypatch.setenv("WATCHDOG_PID", "1")
    assert watchdog_interval_s() is None
    monkeypatch.delenv("WATCHDOG_USEC")
    assert watchdog_interval_s() is None
