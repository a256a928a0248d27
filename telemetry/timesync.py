"""Map a MAVLink component's ``time_boot_ms`` to companion unix µs.

Each component (system id, component id) has its own boot clock. Its messages are split into
*boot epochs* (a reboot makes ``time_boot_ms`` go back by more than ``reboot_backstep_ms``; smaller
steps back are reordering). Per epoch the offset ``unix_us - boot_us`` (optionally with a linear
drift) comes from, in order of preference:

1. TIMESYNC replies to the companion's own requests (``tc1`` = component boot ns, ``ts1`` = the
   companion's send time in ns echoed back, received at the tlog time): the round trip gives
   ``offset = ts1 + rtt/2 - tc1``. Only the lowest-RTT replies per window are used (their latency
   is the most symmetric), NTP-style; jitter and queueing delay drop out.
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
    window_s: float = 5.0
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
    ts_boot, ts_off, ts_rtt = [], [], []
    st_boot, st_off = [], []
    rx_boot, rx_off = [], []
    for i, b in items:
        rec = records[i]
        msg = rec.msg
        t = msg.get_type()
        if t == "TIMESYNC":
            rtt = rec.t_unix_us - msg.ts1 / 1000.0
            if 0 <= rtt <= cfg.max_rtt_us:
                ts_boot.append(b)
                ts_off.append(msg.ts1 / 1000.0 + rtt / 2.0 - b)
                ts_rtt.append(rtt)
            continue
        if t == "SYSTEM_TIME" and msg.time_unix_usec > 946_684_800_000_000:
            st_boot.append(b)
            st_off.append(msg.time_unix_usec - b)
        rx_boot.append(b)
        rx_off.append(rec.t_unix_us - b)
    boots = [b for _, b in items]
    first_ms, last_ms = int(min(boots) // 1000), int(max(boots) // 1000)
    if ts_boot:
        src, boot, off, cost = "timesync", ts_boot, ts_off, ts_rtt
    elif st_boot:
        src, boot, off, cost = "system_time", st_boot, st_off, [0.0] * len(st_boot)
    else:
        # Lower envelope: the least-delayed messages give the smallest recv - boot.
        src, boot, off, cost = "receive_time", rx_boot, rx_off, rx_off
    offset, drift, ref, n = _window_fit(np.array(boot), np.array(off), np.array(cost), cfg,
                                        pick_min=True)
    rtt = float(np.min(ts_rtt)) if src == "timesync" else None
    return Epoch(k, src, offset, drift, ref, n, first_ms, last_ms, rtt)


def _window_fit(boot, off, cost, cfg: TimeSyncConfig, pick_min: bool):
    """Keep the lowest-cost sample per window of boot time; fit offset (+ drift if the span allows)."""
    w = cfg.window_s * 1e6
    keys = np.floor((boot - boot.min()) / w).astype(np.int64)
    sel_b, sel_o = [], []
    for key in np.unique(keys):
        idx = np.nonzero(keys == key)[0]
        j = idx[np.argmin(cost[idx])] if pick_min else idx
        if pick_min and cost is not None and np.all(cost[idx] == 0):
            # SYSTEM_TIME: all samples exact up to quantisation: average them.
            sel_b.append(float(np.mean(boot[idx])))
            sel_o.append(float(np.mean(off[idx])))
        else:
            sel_b.append(float(boot[j]))
            sel_o.append(float(off[j]))
    sb, so = np.array(sel_b), np.array(sel_o)
    ref = float(np.mean(sb))
    if len(sb) >= 3 and sb.max() - sb.min() >= cfg.drift_min_span_s * 1e6:
        drift, offset = np.polyfit(sb - ref, so, 1)
        return float(offset), float(drift), ref, len(sb)
    return float(np.median(so)), 0.0, ref, len(sb)
