"""``derived/report.md``: what a replay found, with the numbers and plots a reader needs.

Sections: timing per stage, poses, field fidelity, synthesis, and the detector table (mAP50 and
mAP50:95 of the Real / Synthetic / R+S models on every test set, with R+S against Real in
percent — the paper's headline comparison). Plots are PNGs beside the report.
"""

from __future__ import annotations

import datetime as _dt
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _fmt(v, digits=3):
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def relative_gain(new: float | None, base: float | None) -> str:
    """``+12.3 %`` of ``new`` over ``base`` (as the paper reports), or ``–`` when undefined."""
    if new is None or base is None:
        return "–"
    if base <= 0:
        return "n/a (Real = 0)" if new > 0 else "±0"
    return f"{100.0 * (new - base) / base:+.1f} %"


def detector_table(table: dict) -> list[str]:
    """Markdown rows: one per test set, columns per model, then R+S vs Real."""
    models = [m for m in ("real", "synthetic", "r+s") if m in table]
    if not models:
        return ["No detector was evaluated."]
    sets = list(next(iter(table.values())).keys())
    head = "| test set | " + " | ".join(f"{m} mAP50 | {m} mAP50:95" for m in models)
    head += " | R+S vs Real (mAP50) | R+S vs Real (mAP50:95) |" if {"real", "r+s"} <= set(models) else " |"
    lines = [head, "|" + "---|" * (1 + 2 * len(models) + (2 if {"real", "r+s"} <= set(models) else 0))]
    for s in sets:
        row = f"| {s} | " + " | ".join(f"{_fmt(table[m][s]['map50'])} | {_fmt(table[m][s]['map50_95'])}"
                                         for m in models)
        if {"real", "r+s"} <= set(models):
            row += (f" | {relative_gain(table['r+s'][s]['map50'], table['real'][s]['map50'])}"
                    f" | {relative_gain(table['r+s'][s]['map50_95'], table['real'][s]['map50_95'])}")
        lines.append(row + " |")
    return lines


def plot_map_vs_altitude(table: dict, out: Path) -> Path | None:
    """mAP50 against test altitude for each training set (only the "N m" test sets)."""
    alt_sets = sorted((float(s.split()[0]), s) for s in next(iter(table.values()), {}) if s.endswith(" m"))
    if not alt_sets:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for model, rows in table.items():
        ax.plot([a for a, _ in alt_sets], [rows[s]["map50"] for _, s in alt_sets], "o-", label=model)
    ax.set_xlabel("test altitude (m)")
    ax.set_ylabel("mAP50")
    ax.set_title("detectors trained at the flight altitude")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def write_report(flight: Path, summaries: dict, stage_seconds: dict, total_s: float) -> Path:
    derived = Path(flight) / "derived"
    derived.mkdir(parents=True, exist_ok=True)
    lines = [f"# uavsim replay report: {Path(flight).name}", "",
             f"Generated {_dt.datetime.now(_dt.UTC).strftime('%Y-%m-%d %H:%M UTC')}; this run took "
             f"{total_s:.0f} s (finished stages reused from earlier runs count as 0).", "",
             "## Stages", "", "| stage | seconds (when it ran) |", "|---|---|"]
    lines += [f"| {k} | {_fmt(v, 1)} |" for k, v in stage_seconds.items()]
    p = summaries.get("poses", {})
    lines += ["", "## Poses", "",
              f"- frames: {p.get('frames')}, posed from telemetry: {p.get('telemetry_posed')} "
              f"(time source: {p.get('time_source')})",
              f"- SfM: {p.get('sfm', 'on')}; refined {_fmt(p.get('sfm_refined'))} frames, mean reprojection "
              f"{_fmt(p.get('mean_reprojection_px'))} px, {p.get('points', '–')} sparse points"]
    f = summaries.get("fit", {})
    kind = f.get("kind", "static")
    title = {"static": "static, with mask head", "kplanes": "dynamic: K-Planes",
             "kplanes-ext": "dynamic: extended K-Planes, with mask channel"}.get(kind, kind)
    lines += ["", f"## Radiance field ({title})", ""]
    if f.get("kind_reason"):
        lines.append(f"- kind chosen from the flight: {f['kind_reason']}")
    lines += [f"- held-out PSNR {_fmt(f.get('heldout_psnr'), 2)} dB, SSIM {_fmt(f.get('heldout_ssim'))}, "
              f"mask box IoU {_fmt(f.get('heldout_box_iou'))}",
              f"- {f.get('steps')} steps in {_fmt(f.get('train_s'), 0)} s; {f.get('params')} parameters "
              f"({f.get('mb')} MB); details in `derived/fields/fit.json`"]
    s = summaries.get("synth", {})
    lines += ["", "## Synthetic data", "",
              f"- {s.get('images')} novel views, {s.get('boxes')} boxes from mask blobs "
              f"({s.get('boxes_per_class')}), {s.get('empty_images')} without people, "
              f"{s.get('dropped_poses')} candidate poses dropped (outside the observed region)",
              f"- {s.get('images_per_minute')} images per minute",
              "", "![contact sheet](synth/contact_sheet.png)"]
    table = summaries.get("eval", {}).get("table", {})
    lines += ["", "## Detectors: Real / Synthetic / R+S", ""]
    base = next((summaries[k].get("base") for k in summaries if k.startswith("train-")), None)
    if base:
        from export.pretrain import base_info

        info = base_info(base)
        lines += [f"Each detector is fine-tuned from the base detector `{base}` (YOLOv8n trained from scratch on "
                  f"simulator renders of other worlds at 15 m; its own val mAP50 "
                  f"{_fmt(info.get('val_map50'))}), as the paper fine-tunes a pretrained YOLOv8n.", ""]
    elif any(k.startswith("train-") for k in summaries):
        lines += ["**Trained from scratch on this flight only (no base detector)**: a few dozen images cannot "
                  "train YOLOv8n, so these numbers say nothing about synthetic data; run "
                  "`uavsim detector pretrain` once and replay again.", ""]
    lines += detector_table(table)
    plot = plot_map_vs_altitude(table, derived / "map_vs_altitude.png") if table else None
    if plot:
        lines += ["", "![mAP50 against altitude](map_vs_altitude.png)"]
    for name in ("real", "synthetic", "r+s"):
        t = summaries.get(f"train-{name}")
        if t:
            m = t.get("metrics", {})
            steps = m.get("optimizer_steps")
            lines.append(f"- {name}: best epoch {m.get('best_epoch')} (val mAP50 {_fmt(m.get('map50'))}), "
                         f"trained {_fmt(m.get('seconds'), 0)} s"
                         + (f", {steps} optimizer steps" if steps is not None else ""))
    out = derived / "report.md"
    out.write_text("\n".join(lines) + "\n")
    log.info("report written to %s", out)
    return out
