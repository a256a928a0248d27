import numpy as np
import pytest

from telemetry.timesync import TimeSyncConfig, build_clock_maps

from .tlogfactory import T0, TlogBuilder, heartbeat_autopilot, m


def jittery_link(duration_s=120.0, drift_ppm=40.0, seed=0, timesync=True, system_time=True):
    """Autopilot boot clock with drift; every message and TIMESYNC leg has 15-45 ms random latency."""
    rng = np.random.default_rng(seed)
    boot0 = T0 - 77_000_000

    def boot_us(t):
        return (t - boot0) * (1 + drift_ppm * 1e-6)

    b = TlogBuilder()
    b.add(T0, heartbeat_autopilot())
    for k in range(int(duration_s * 10)):
        t = T0 + k * 100_000
        lat = int(rng.uniform(15_000, 45_000))
        b.add(t + lat, m.MAVLink_attitude_message(int(boot_us(t) // 1000), 0, 0, 0, 0, 0, 0))
        if system_time and k % 10 == 0:
            b.add(t + lat, m.MAVLink_system_time_message(t, int(boot_us(t) // 1000)))
        if timesync and k % 2 == 0:
            up, down = rng.uniform(15_000, 45_000, 2).astype(int)
            b.add(t + up + down, m.MAVLink_timesync_message(int(boot_us(t + up) * 1000), t * 1000))
    b.items.sort(key=lambda it: it[0])
    return b, boot_us


def max_error_us(cmap, records, boot_us):
    """Largest |mapped - true| companion time over the ATTITUDE messages."""
    errs = []
    for i, rec in enumerate(records):
        if rec.msg.get_type() != "ATTITUDE":
            continue
        mapped = cmap.unix_us(i)
        # true companion time of the message: invert the drifting boot clock at boot_ms + 0.5 ms
        b_us = rec.msg.time_boot_ms * 1000 + 500
        lo, hi = T0 - 10**8, T0 + 10**9
        for _ in range(60):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if boot_us(mid) < b_us else (lo, mid)
        errs.append(abs(mapped - lo))
    return max(errs)


def test_timesync_with_jitter_and_drift_is_sub_millisecond():
    b, boot_us = jittery_link()
    recs = b.records()
    cmap = build_clock_maps(recs)[(1, 1)]
    assert cmap.source == "timesync" and len(cmap.epochs) == 1
    assert cmap.epochs[0].drift * 1e6 == pytest.approx(-40.0, abs=20.0)  # what matters is the time error below
    assert max_error_us(cmap, recs, boot_us) < 1500  # ±0.5 ms quantisation + bounds


def test_system_time_without_timesync():
    b, boot_us = jittery_link(timesync=False)
    recs = b.records()
    cmap = build_clock_maps(recs)[(1, 1)]
    assert cmap.source == "system_time"
    assert max_error_us(cmap, recs, boot_us) < 1500


def test_receive_time_fallback_is_biased_by_the_fastest_latency_only():
    b, boot_us = jittery_link(timesync=False, system_time=False, drift_ppm=0.0)
    recs = b.records()
    cmap = build_clock_maps(recs)[(1, 1)]
    assert cmap.source == "receive_time" and cmap.warnings
    err = max_error_us(cmap, recs, boot_us)
    assert 14_000 < err < 17_000  # the minimum latency (15 ms) cannot be seen from receive times


def test_window_and_reboot_thresholds_are_configurable():
    b, _ = jittery_link(duration_s=20.0)
    recs = b.records()
    cfg = TimeSyncConfig(window_s=1.0, drift_min_span_s=5.0)
    assert build_clock_maps(recs, cfg)[(1, 1)].epochs[0].n_samples == 20
