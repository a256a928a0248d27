"""Map a MAVLink component's ``time_boot_ms`` to companion unix µs.

Each component (system id, component id) has its own boot clock. Its messages are split into
*boot epochs* (a reboot makes ``time_boot_ms`` go back by more than ``reboot_backstep_ms``; smaller
steps back are reordering). Per epoch the offset ``unix_us - boot_us`` (optionally with a linear
drift) comes from, in order of preference:

1. TIMESYNC replies to the companion's own requests (``tc1`` = component boot ns, ``ts1`` = the
   companion's send time in ns echoed back, received at the tlog time): each round trip bounds
   the offset, ``ts1 - tc1 <= offset <= recv - tc1``; per window the bounds are intersected and
   the middle taken (NTP-style), so jitter and queueing delay drop out.
2. SYSTEM_TIME (``time_unix_usec`` at ``time_boot_ms``): the autopilot's GPS-disciplined clock;
   assumes the companion clock is synchronised to UTC (NTP/GPS), logged at info level.
3. Receive times (lower envelope of ``recv_us - boot_us``, i.e. assuming the fastest messages had no
   latency): the fallback, logged as a warning because the link latency then biases every time.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

SOURCES = ("timesync", "system_time", "receive_time")


@dataclass
class TimeSyncConfig:
    """Tuning of :func:`build_clock_maps`."""

    #: a step back of time_boot_ms larger than this (ms) is a reboot; smaller ones are reordering.
    reboot_backstep_ms: int = 2000
    #: window (s of boot time) in which the best sample is kept; a line is fitted through the windows.
    window_s: float = 10.0
    #: fit a clock drift (linear term) when the samples span at least this many seconds.
    drift_min_span_s: float = 30.0
    #: TIMESYNC replies with a round trip longer than this (µs) are ignored.
    max_rtt_us: int = 1_000_000


@dataclass
class Epoch:
    """One boot of a component: ``unix_us = boot_us + offset_us + drift * (boot_us - ref_boot_us)``."""

    index: int
    source: str
    offset_us: float
    drift: float
    ref_boot_us: float
    n_samples: int
    boot_ms_first: int
    boot_ms_last: int
    rtt_us: float | None = None

    def to_unix_us(self, boot_us: float) -> int:
        return int(round(boot_us + self.offset_us + self.drift * (boot_us - self.ref_boot_us)))


@dataclass
class ClockMap:
    """Boot epochs of one component and the epoch of each of its boot-timed records."""

    component: tuple[int, int]
    epochs: list[Epoch]
    #: record index (in the tlog) -> (epoch index, boot µs)
    record_boot: dict[int, tuple[int, float]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def unix_us(self, record_index: int) -> int | None:
        """Companion unix µs of a boot-timed record of this component (None if it has no boot time)."""
        eb = self.record_boot.get(record_index)
        if eb is None:
            return None
        return self.epochs[eb[0]].to_unix_us(eb[1])

    @property
    def source(self) -> str:
        """The weakest source used by any epoch (what a summary should show)."""
        if not self.epochs:
            return "none"
        return max((e.source for e in self.epochs), key=SOURCES.index)


def boot_us_of(msg) -> float | None:
    """Boot time (µs) a message carries: ``time_boot_ms`` or a TIMESYNC reply's ``tc1``."""
    t = msg.get_type()
    if t == "TIMESYNC":
        return msg.tc1 / 1000.0 if msg.tc1 > 0 else None
    ms = getattr(msg, "time_boot_ms", None)
    if ms is None:
        return None
    # time_boot_ms is truncated to whole ms: the event happened on average half a ms later.
    return ms * 1000.0 + 500.0


def build_clock_maps(records, config: TimeSyncConfig | None = None) -> dict[tuple[int, int], ClockMap]:
    """One :class:`ClockMap` per (system, component) that sends boot-timed messages.

    ``records``: sequence of objects with ``t_unix_us`` (receive time) and ``msg`` (pymavlink message),
    in receive order, e.g. :class:`telemetry.mavlink.TlogRecord`.
    """
    cfg = config or TimeSyncConfig()
    per_comp: dict[tuple[int, int], list[tuple[int, float]]] = {}
    for i, rec in enumerate(records):
        b = boot_us_of(rec.msg)
        if b is None:
            continue
        per_comp.setdefault((rec.msg.get_srcSystem(), rec.msg.get_srcComponent()), []).append((i, b))
    return {comp: _build_one(comp, items, records, cfg) for comp, items in per_comp.items()}


def _build_one(comp, items, records, cfg: TimeSyncConfig) -> ClockMap:
    # Split into boot epochs in receive order.
    epoch_items: list[list[tuple[int, float]]] = [[]]
    max_boot = -np.inf
    for i, b in items:
        if b < max_boot - cfg.reboot_backstep_ms * 1000.0:
            epoch_items.append([])
            max_boot = -np.inf
        epoch_items[-1].append((i, b))
        max_boot = max(max_boot, b)
    cmap = ClockMap(component=comp, epochs=[])
    if len(epoch_items) > 1:
        msg = f"component {comp}: time_boot_ms went back {len(epoch_items) - 1} time(s): autopilot reboot"
        cmap.warnings.append(msg)
        log.warning("%s", msg)
    for k, ep in enumerate(epoch_items):
        epoch = _fit_epoch(k, ep, records, cfg)
        if epoch.source == "receive_time":
            msg = (f"component {comp} epoch {k}: no TIMESYNC or SYSTEM_TIME; boot times mapped with "
                   "receive times (biased by link latency)")
            cmap.warnings.append(msg)
            log.warning("%s", msg)
        elif epoch.source == "system_time":
            log.info("component %s epoch %d: mapped through SYSTEM_TIME (assumes a UTC-synchronised "
                     "companion clock)", comp, k)
        cmap.epochs.append(epoch)
        for i, b in ep:
            cmap.record_boot[i] = (k, b)
    return cmap


def _fit_epoch(k: int, items, records, cfg: TimeSyncConfig) -> Epoch:
    ts_boot, ts_lo, ts_hi = [], [], []
    st_boot, st_off = [], []
    rx_boot, rx_hi = [], []
    for i, b in items:
        rec = records[i]
        msg = rec.msg
        t = msg.get_type()
        if t == "TIMESYNC":
            rtt = rec.t_unix_us - msg.ts1 / 1000.0
            if 0 <= rtt <= cfg.max_rtt_us:
                # the reply was made after our request left and before it came back:
                # ts1 - tc1 <= offset <= recv - tc1
                ts_boot.append(b)
                ts_lo.append(msg.ts1 / 1000.0 - b)
                ts_hi.append(rec.t_unix_us - b)
            continue
        if t == "SYSTEM_TIME" and msg.time_unix_usec > 946_684_800_000_000:
            st_boot.append(b)
            st_off.append(msg.time_unix_usec - b)
        # a message cannot arrive before it was made: offset <= recv - true boot (>= b - 500)
        rx_boot.append(b)
        rx_hi.append(rec.t_unix_us - (b - 500.0))
    boots = [b for _, b in items]
    first_ms, last_ms = int(min(boots) // 1000), int(max(boots) // 1000)
    if ts_boot:
        src = "timesync"
        sb, so = _bounds_windows(np.array(ts_boot), np.array(ts_lo), np.array(ts_hi), cfg)
    elif st_boot:
        src = "system_time"
        sb, so = _windows(np.array(st_boot), np.array(st_off), cfg, np.mean)
    else:
        # Lower envelope: the least-delayed messages give the smallest recv - boot.
        src = "receive_time"
        sb, so = _windows(np.array(rx_boot), np.array(rx_hi), cfg, np.min)
    offset, drift, ref = _fit_line(sb, so, cfg)
    rtt = float(np.min(np.array(ts_hi) - np.array(ts_lo))) if src == "timesync" else None
    return Epoch(k, src, offset, drift, ref, len(sb), first_ms, last_ms, rtt)


def _window_keys(boot: np.ndarray, t0: float, cfg: TimeSyncConfig) -> np.ndarray:
    return np.floor((boot - t0) / (cfg.window_s * 1e6)).astype(np.int64)


def _windows(boot, off, cfg: TimeSyncConfig, reduce) -> tuple[np.ndarray, np.ndarray]:
    keys = _window_keys(boot, boot.min(), cfg)
    sb, so = [], []
    for key in np.unique(keys):
        idx = keys == key
        sb.append(float(np.mean(boot[idx])))
        so.append(float(reduce(off[idx])))
    return np.array(sb), np.array(so)


def _bounds_windows(ts_boot, ts_lo, ts_hi, cfg: TimeSyncConfig):
    """Per window: intersect the hard bounds on the offset that TIMESYNC round trips give (NTP-style)
    and take the middle.

    Each reply bounds the offset from below (uplink latency >= 0) and above (downlink latency >= 0).
    Over a window the tightest bounds come from the fastest up- and the fastest downlink; the
    middle is unbiased when those are equal, which holds for a request and a reply of the same size
    on the same link, whatever the jitter. (Telemetry messages are not used as bounds: their
    latency differs from TIMESYNC's and would bias the middle.) Inconsistent bounds (a clock step)
    fall back to the lowest-round-trip reply.
    """
    k_ts = _window_keys(ts_boot, ts_boot.min(), cfg)
    sb, so = [], []
    for key in np.unique(k_ts):
        i = k_ts == key
        lo, hi = float(ts_lo[i].max()), float(ts_hi[i].min())
        if lo <= hi:
            off = 0.5 * (lo + hi)
        else:
            j = np.argmin(ts_hi[i] - ts_lo[i])
            off = 0.5 * (ts_lo[i][j] + ts_hi[i][j])
        sb.append(float(np.mean(ts_boot[i])))
        so.append(off)
    return np.array(sb), np.array(so)


def _fit_line(sb: np.ndarray, so: np.ndarray, cfg: TimeSyncConfig) -> tuple[float, float, float]:
    """offset at ref + drift (fitted only when the windows span long enough)."""
    ref = float(np.mean(sb))
    if len(sb) >= 3 and sb.max() - sb.min() >= cfg.drift_min_span_s * 1e6:
        drift, offset = np.polyfit(sb - ref, so, 1)
        return float(offset), float(drift), ref
    return float(np.median(so)), 0.0, ref
