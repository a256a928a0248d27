"""``uavsim demo``: the main job on the built-in simulated flight.

A 15 m orbit over the simulated world is recorded through the real logger with the simulated
autopilot and camera (``sim-flight``), then replayed: telemetry poses refined by SfM, a static
field with a mask head, synthetic views at 35-50 m with boxes from mask blobs, and three
detectors (Real, Synthetic, R+S) trained at 15 m and tested on simulator-rendered sets at
15/35/40/45/50 m — the paper's static experiment. Everything lands in ``OUT/flight/derived/``;
the report is ``OUT/flight/derived/report.md``.

``--quick`` shrinks every stage (smaller images, fewer frames, short budgets) to finish in
minutes on 2 CPU cores; the full run states its time at the end.

The detectors are fine-tuned from a base detector (:mod:`export.pretrain`: YOLOv8n trained once on
simulator renders of *other* worlds at 15 m, cached), the stand-in for the paper's COCO-pretrained
weights. The full demo trains that base first when it is not cached yet (about an hour on 2 cores);
the quick demo uses it when present and otherwise trains from scratch and says that its detectors
cannot be meaningful.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoPlan:
    frames: int
    width: int
    height: int
    fit_budget_s: float
    synth_count: int  # 0: as many as real training frames (the paper)
    epochs: int
    imgsz: int
    batch: int
    test_images: int
    sfm: bool
    train_budget_s: float | None


QUICK = DemoPlan(frames=32, width=320, height=240, fit_budget_s=150.0, synth_count=16, epochs=8, imgsz=320,
                 batch=8, test_images=8, sfm=True, train_budget_s=45.0)
FULL = DemoPlan(frames=60, width=640, height=480, fit_budget_s=300.0, synth_count=0, epochs=20, imgsz=640,
                batch=16, test_images=40, sfm=True, train_budget_s=None)


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="simulated flight → full pipeline → report (the main job)")
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    p.add_argument("--quick", action="store_true", help="small and fast (minutes on 2 cores)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="rerun finished stages")
    p.add_argument("--base", default="auto", help="detector to fine-tune from: auto (the cached base; the full demo "
                                                  "trains it when missing), none (from scratch), or a .pt path")
    p.set_defaults(func=run_cli)


def demo_base(choice: str, quick: bool) -> str | None:
    """The base detector for the demo's fine-tuning (None: from scratch), training it for the full demo."""
    from agent.replay import resolve_base
    from export.pretrain import PretrainConfig, default_base_dir, find_base, pretrain_base

    if choice.lower() == "auto" and not quick and find_base(None) is None:
        log.info("no cached base detector: training it first (%s; about an hour on 2 cores, once)",
                 default_base_dir())
        pretrain_base(PretrainConfig())
    return resolve_base(choice)


def run_cli(args) -> int:
    from agent.replay import ReplayOptions, replay
    from sim.flight import SimFlightConfig, run_sim_flight, truth_path

    plan = QUICK if args.quick else FULL
    t0 = time.perf_counter()
    base = demo_base(args.base, args.quick)
    out: Path = args.out
    flight = out / "flight"
    if not (flight / "frames.csv").is_file():
        out.mkdir(parents=True, exist_ok=True)
        log.info("recording the simulated flight (%d frames, %dx%d)", plan.frames, plan.width, plan.height)
        run_sim_flight(flight, SimFlightConfig(frames=plan.frames, width=plan.width, height=plan.height,
                                               seed=args.seed, noise="realistic"),
                       progress=lambda k, n: log.info("frame %d/%d", k, n) if k % 10 == 0 or k == n else None)
    else:
        log.info("%s already recorded: reusing it (delete it to record again)", flight)
    opts = ReplayOptions(seed=args.seed, force=args.force, kind="static", sfm=plan.sfm, fit_budget_s=plan.fit_budget_s,
                         synth_count=plan.synth_count, epochs=plan.epochs, imgsz=plan.imgsz, batch=plan.batch,
                         train_budget_s=plan.train_budget_s, truth=str(truth_path(flight)),
                         test_images_per_altitude=plan.test_images, base_weights=base)
    result = replay(flight, opts)
    minutes = (time.perf_counter() - t0) / 60
    print(f"demo finished in {minutes:.1f} min: {result['report']}")
    print(f"detectors fine-tuned from {base}" if base else
          "detectors trained from scratch on this flight only (no base detector): expect ~0 mAP; "
          "`uavsim detector pretrain` once makes them meaningful")
    table = result["summaries"].get("eval", {}).get("table", {})
    for model, rows in table.items():
        print(f"  {model:>9}: " + ", ".join(f"{s} mAP50 {r['map50']:.3f}" for s, r in rows.items()))
    return 0
