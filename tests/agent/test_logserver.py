"""Ground-station log download over real HTTP: auth, listing, Range resume, streamed tar, escapes."""

import io
import json
import os
import tarfile
import urllib.error
import urllib.request

import pytest

from agent.logserver import LogServer, TokenFileError, load_token

TOKEN = "s3cret-token-0123456789"


@pytest.fixture
def server(tmp_path):
    root = tmp_path / "flights"
    f = root / "flight_0001"
    (f / "frames").mkdir(parents=True)
    (f / "frames.csv").write_text("frame,t_unix_us\n000000.jpg,1700000000000000\n000001.jpg,1700000000100000\n")
    (f / "frames" / "000000.jpg").write_bytes(os.urandom(5000))
    (f / "frames" / "000001.jpg").write_bytes(os.urandom(700))
    (f / "telemetry.tlog").write_bytes(bytes(range(256)) * 40)
    (tmp_path / "secret.txt").write_text("not yours")
    (f / "link_out").symlink_to(tmp_path / "secret.txt")
    (root / "linked_flight").symlink_to(f)
    srv = LogServer(root, TOKEN, status=lambda: {"state": "idle"})
    port = srv.start_in_thread()
    yield f"http://127.0.0.1:{port}", f
    srv.stop()


def _get(url, token=TOKEN, headers=None):
    h = dict(headers or {})
    if token:
        h["Authorization"] = f"Bearer {token}"
    req = urllib.request.Request(url, headers=h)
    with urllib.request.urlopen(req, timeout=10) as resp:
        return resp.status, dict(resp.headers), resp.read()


def _status(url, token=TOKEN):
    try:
        return _get(url, token)[0]
    except urllib.error.HTTPError as exc:
        return exc.code


def test_health_needs_no_token_but_everything_else_does(server):
    base, _ = server
    assert _get(base + "/api/health", token=None)[0] == 200
    for path in ("/api/status", "/api/flights", "/api/flights/flight_0001",
                 "/api/flights/flight_0001/archive", "/api/flights/flight_0001/files/frames.csv"):
        assert _status(base + path, token=None) == 401
        assert _status(base + path, token="wrong-token-wrong-token") == 401
    assert json.loads(_get(base + "/api/status")[2]) == {"state": "idle"}


def test_list_and_details(server):
    base, f = server
    flights = json.loads(_get(base + "/api/flights")[2])["flights"]
    assert [x["id"] for x in flights] == ["flight_0001"]  # the symlinked flight is not listed
    assert flights[0]["frames"] == 2 and flights[0]["start_unix_us"] == 1700000000000000
    details = json.loads(_get(base + "/api/flights/flight_0001")[2])
    paths = [x["path"] for x in details["file_list"]]
    assert paths == ["frames.csv", "telemetry.tlog", "frames/000000.jpg", "frames/000001.jpg"]
    assert details["size_bytes"] == sum(x["size_bytes"] for x in details["file_list"])


def test_range_request_resumes_exactly(server):
    base, f = server
    full = (f / "frames" / "000000.jpg").read_bytes()
    status, _, first = _get(base + "/api/flights/flight_0001/files/frames/000000.jpg",
                            headers={"Range": "bytes=0-1999"})
    assert status == 206 and first == full[:2000]
    status, headers, rest = _get(base + "/api/flights/flight_0001/files/frames/000000.jpg",
                                 headers={"Range": "bytes=2000-"})
    assert status == 206 and first + rest == full
    assert headers["Content-Range"] == f"bytes 2000-4999/{len(full)}"


def test_archive_is_a_complete_tar(server):
    base, f = server
    status, headers, body = _get(base + "/api/flights/flight_0001/archive")
    assert status == 200 and headers["Content-Type"] == "application/x-tar"
    with tarfile.open(fileobj=io.BytesIO(body)) as tar:
        names = tar.getnames()
        assert "flight_0001/telemetry.tlog" in names and "flight_0001/link_out" not in names
        assert tar.extractfile("flight_0001/frames/000000.jpg").read() == (f / "frames" / "000000.jpg").read_bytes()


@pytest.mark.parametrize("path", [
    "/api/flights/flight_0001/files/../../secret.txt",
    "/api/flights/flight_0001/files/%2e%2e/%2e%2e/secret.txt",
    "/api/flights/flight_0001/files/frames/%2e%2e/%2e%2e/secret.txt",
    "/api/flights/flight_0001/files/link_out",
    "/api/flights/flight_0001/files//etc/passwd",
    "/api/flights/flight_0001/files/frames",
    "/api/flights/..%2f..%2fsecret.txt/archive",
    "/api/flights/linked_flight/files/frames.csv",
    "/api/flights/nope/archive",
])
def test_escapes_and_missing_are_404(server, path):
    base, _ = server
    assert _status(base + path) == 404


def test_read_only(server):
    base, _ = server
    req = urllib.request.Request(base + "/api/flights/flight_0001/files/frames.csv", method="DELETE",
                                 headers={"Authorization": f"Bearer {TOKEN}"})
    with pytest.raises(urllib.error.HTTPError) as exc:
        urllib.request.urlopen(req, timeout=10)
    assert exc.value.code == 405


def test_token_file_must_be_private(tmp_path):
    p = tmp_path / "token"
    p.write_text(TOKEN + "\n")
    p.chmod(0o644)
    with pytest.raises(TokenFileError, match="chmod 600"):
        load_token(p)
    p.chmod(0o600)
    assert load_token(p) == TOKEN
    p.write_text("short")
    with pytest.raises(TokenFileError, match="16 characters"):
        load_token(p)
    with pytest.raises(TokenFileError, match="not found"):
        load_token(tmp_path / "missing")


def _post(url, token=TOKEN):
    req = urllib.request.Request(url, data=b"", method="POST",
                                 headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        return exc.code, None


def test_processing_requests_reach_the_agent_only_with_the_token_and_a_real_flight(tmp_path):
    root = tmp_path / "flights"
    (root / "flight_0001").mkdir(parents=True)
    asked = []
    srv = LogServer(root, TOKEN, request_processing=lambda d: (asked.append(d.name), (202, {"queued": d.name}))[1])
    base = f"http://127.0.0.1:{srv.start_in_thread()}"
    try:
        assert _post(base + "/api/flights/flight_0001/process", token=None)[0] == 401
        assert _post(base + "/api/flights/..%2F..%2Fetc/process")[0] == 404
        assert _post(base + "/api/flights/flight_9999/process")[0] == 404
        assert _post(base + "/api/flights/flight_0001/process") == (202, {"queued": "flight_0001"})
        assert asked == ["flight_0001"]
    finally:
        srv.stop()


def test_without_a_processing_callback_the_api_has_no_post_route(server):
    base, _ = server
    assert _post(base + "/api/flights/flight_0001/process")[0] in (404, 405)
