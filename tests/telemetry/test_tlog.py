import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telemetry.frames import euler_zyx_to_matrix
from telemetry.mavlink import parse_tlog_bytes, read_tlog
from telemetry.quat import matrix_to_quat, quat_to_matrix, rotation_angle_deg, slerp

from .tlogfactory import T0, TlogBuilder, factory_flight


def flight_bytes(duration_s=2.0):
    b = TlogBuilder()
    factory_flight(b, duration_s=duration_s)
    return b.data(), len(b.items)


def test_round_trip_all_messages():
    data, n = flight_bytes()
    res = parse_tlog_bytes(data)
    assert len(res.records) == n and not res.problems
    assert res.records[0].t_unix_us == T0


def test_truncated_tail_is_reported_and_the_rest_kept(tmp_path):
    data, n = flight_bytes()
    for cut in (1, 5, 9, 20):
        res = parse_tlog_bytes(data[:-cut])
        assert res.truncated_tail
        assert len(res.records) == n - 1
        assert any("truncated" in p for p in res.problems)
    p = tmp_path / "t.tlog"
    p.write_bytes(data[:-3])
    assert read_tlog(p).truncated_tail


def test_garbage_between_records_is_skipped_and_parser_resyncs():
    data, n = flight_bytes()
    rng = np.random.default_rng(0)
    junk = rng.integers(0, 256, 300, dtype=np.uint8).tobytes()
    half = len(data) // 2
    # find a record boundary near the middle: records start with the 8-byte timestamp
    res0 = parse_tlog_bytes(data)
    offs, pos = [], 0
    for r in res0.records:
        offs.append(pos)
        pos += 8 + len(r.raw)
    cut = min(offs, key=lambda o: abs(o - half))
    res = parse_tlog_bytes(data[:cut] + junk + data[cut:])
    assert len(res.records) >= n - 1
    assert res.bytes_skipped > 0


def test_corrupted_crc_frame_is_skipped():
    data, n = flight_bytes()
    buf = bytearray(data)
    buf[8 + 12] ^= 0xFF  # a payload byte of the first frame
    res = parse_tlog_bytes(bytes(buf))
    assert len(res.records) == n - 1 and res.bad_crc >= 1


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=2000))
def test_random_bytes_never_crash(blob):
    res = parse_tlog_bytes(blob)
    assert res.bytes_total == len(blob)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 3000), st.binary(min_size=1, max_size=50))
def test_random_insertions_never_crash_and_keep_most(pos, junk):
    data, n = flight_bytes(1.0)
    pos = min(pos, len(data))
    res = parse_tlog_bytes(data[:pos] + junk + data[pos:])
    assert len(res.records) >= n - 2


@pytest.mark.parametrize("magic", [b"\xfe", b"\xfd"])
def test_junk_that_looks_like_an_over_long_frame_does_not_end_the_log(magic):
    """Magic bytes inserted before a frame read as a 254-byte frame running past the end of the
    file; that is junk, not a truncated tail, when readable records follow (found by hypothesis:
    it used to drop every record after it)."""
    data, n = flight_bytes(1.0)
    good = parse_tlog_bytes(data).records
    starts = np.cumsum([0] + [8 + len(r.raw) for r in good])
    k = len(good) - 8
    pos = int(starts[k]) + 8  # between record k's timestamp and its frame
    res = parse_tlog_bytes(data[:pos] + magic * 12 + data[pos:])
    assert not res.truncated_tail
    assert [r.raw for r in res.records] == [r.raw for i, r in enumerate(good) if i != k]
    assert res.bytes_skipped > 0


def test_empty_file():
    res = parse_tlog_bytes(b"")
    assert res.records == [] and not res.truncated_tail


def test_implausible_timestamps_are_skipped():
    data, n = flight_bytes(0.5)
    bad = struct.pack(">Q", 12345) + data[8:]
    res = parse_tlog_bytes(bad)
    assert len(res.records) == n - 1


# ---- quaternions -------------------------------------------------------------------------------
def test_quaternion_round_trip_including_nadir_and_half_turns():
    for ypr in [(0, 0, 0), (np.pi, 0, 0), (0.3, -np.pi / 2, 0), (-2.9, 0.4, np.pi), (1.0, np.pi / 2, 0.2)]:
        R = euler_zyx_to_matrix(*ypr)
        np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)


def test_slerp_takes_the_short_way_across_yaw_wrap_and_sign_flip():
    qa = matrix_to_quat(euler_zyx_to_matrix(np.radians(179.0), 0, 0))
    qb = -matrix_to_quat(euler_zyx_to_matrix(np.radians(-179.0), 0, 0))
    mid = quat_to_matrix(slerp(qa, qb, 0.5))
    assert rotation_angle_deg(mid, euler_zyx_to_matrix(np.pi, 0, 0)) < 1e-9
    for u in np.linspace(0, 1, 11):
        R = quat_to_matrix(slerp(qa, qb, u))
        assert rotation_angle_deg(R, euler_zyx_to_matrix(np.pi, 0, 0)) <= 1.0 + 1e-9


@settings(max_examples=50, deadline=None)
@given(st.floats(-np.pi, np.pi), st.floats(-1.5, 1.5), st.floats(-np.pi, np.pi), st.floats(0, 1))
def test_slerp_angle_is_linear(yaw, pitch, roll, u):
    q0 = matrix_to_quat(euler_zyx_to_matrix(yaw, pitch, roll))
    q1 = matrix_to_quat(euler_zyx_to_matrix(yaw + 0.3, pitch * 0.5, roll - 0.2))
    R0, R1, Ru = quat_to_matrix(q0), quat_to_matrix(q1), quat_to_matrix(slerp(q0, -q1, u))
    total = rotation_angle_deg(R0, R1)
    assert abs(rotation_angle_deg(R0, Ru) - u * total) < 1e-4


def test_vectorised_euler_quaternions_match_matrices():
    from telemetry.quat import euler_zyx_to_quat

    rng = np.random.default_rng(0)
    ypr = rng.uniform(-3, 3, (50, 3)) * [1, 0.5, 1]
    q = euler_zyx_to_quat(ypr[:, 0], ypr[:, 1], ypr[:, 2])
    for (y, p, r), qi in zip(ypr, q, strict=True):
        np.testing.assert_allclose(quat_to_matrix(qi), euler_zyx_to_matrix(y, p, r), atol=1e-12)


def test_junk_read_as_an_unknown_message_does_not_swallow_the_records_it_covers():
    """Junk after a magic byte read as a signed 221-byte frame of unknown id (whose CRC cannot be
    checked) that ends exactly on a record boundary; the records inside it are kept (found by hypothesis)."""
    data, n = flight_bytes(1.0)
    pos = 283
    junk = b"\xc4\x01\x00\x00\x00\x00\x00\x00\x01\x00\x00\x00\x00\x00\x00"
    res = parse_tlog_bytes(data[:pos] + junk + data[pos:])
    assert len(res.records) == n - 1
    assert not res.unknown_ids
