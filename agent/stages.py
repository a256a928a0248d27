"""Resumable processing stages for ``uavsim replay`` and the agent's processing state.

Each finished stage leaves ``derived/stages/NAME.json`` (its summary, duration, seed), written
atomically. On the next run a finished stage is skipped and its summary reused, unless forced;
once any stage actually runs, every later stage runs too, since its inputs may have changed.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)


class StageRunner:
    def __init__(self, flight_dir: str | Path, seed: int = 0, force: bool = False):
        self.flight = Path(flight_dir)
        self.dir = self.flight / "derived" / "stages"
        self.seed = seed
        self.force = force
        self._ran_one = False
        self.summaries: dict[str, dict] = {}

    def marker(self, name: str) -> Path:
        return self.dir / f"{name}.json"

    def run(self, name: str, fn: Callable[[], dict]) -> dict:
        """Run ``fn`` (returns a JSON-able summary) unless the stage already finished."""
        marker = self.marker(name)
        if marker.is_file() and not self.force and not self._ran_one:
            try:
                summary = json.loads(marker.read_text())["summary"]
                log.info("stage %s: done before, skipped (--force reruns)", name)
                self.summaries[name] = summary
                return summary
            except (json.JSONDecodeError, KeyError):
                log.warning("stage %s: unreadable marker, running again", name)
        log.info("stage %s: running", name)
        t0 = time.perf_counter()
        summary = fn()
        seconds = time.perf_counter() - t0
        self._ran_one = True
        self.dir.mkdir(parents=True, exist_ok=True)
        tmp = marker.with_suffix(".tmp")
        tmp.write_text(json.dumps({"stage": name, "seconds": round(seconds, 3), "seed": self.seed,
                                   "finished_unix": time.time(), "summary": summary}, indent=1) + "\n")
        os.replace(tmp, marker)
        log.info("stage %s: finished in %.1f s", name, seconds)
        self.summaries[name] = summary
        return summary

    def seconds(self, name: str) -> float | None:
        try:
            return float(json.loads(self.marker(name).read_text())["seconds"])
        except (OSError, ValueError, KeyError):
            return None
