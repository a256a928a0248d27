"""The mask threshold calibrated on held-out frames, and how `uavsim synth` picks it up."""

import json
import shutil

import numpy as np
import pytest

from agent.cli import main
from fields.mask_boxes import MaskBox
from fields.mask_calibration import HIGH_ALTITUDE_OFFSET, MAX_THRESHOLD, THRESHOLDS, calibrate_threshold
from fields.synth_flight import calibrated_threshold, synthesize_flight


def _soft_person(h=40, w=40, box=(10, 8, 18, 24), rim=0.7, nan_at=None):
    """Class probabilities (H, W, 2): foreground 1 inside ``box`` (x0, y0, x1, y1), ``rim`` on a 1 px ring around it."""
    x0, y0, x1, y1 = box
    fg = np.zeros((h, w), np.float32)
    fg[y0 - 1:y1 + 1, x0 - 1:x1 + 1] = rim
    fg[y0:y1, x0:x1] = 1.0
    if nan_at is not None:
        fg[nan_at] = np.nan
    return np.stack([1.0 - fg, fg], axis=-1)


def _truth(box=(10, 8, 18, 24)):
    return [MaskBox(0, *box, 0, 1.0)]


def test_a_rim_below_the_cut_is_left_out_and_synthesis_cuts_higher():
    c = calibrate_threshold({0: _soft_person(rim=0.7)}, {0: _truth()})
    assert c["heldout_best"] == 0.75  # the lowest cut above the 0.7 rim: the box is exact
    assert c["box_iou"]["0.75"] == 1.0 and c["box_iou"]["0.70"] < 1.0
    assert c["synth_threshold"] == pytest.approx(0.75 + HIGH_ALTITUDE_OFFSET)
    assert c["frames"] == 1 and c["boxes"] == 1
    assert set(c["box_iou"]) == {f"{t:.2f}" for t in THRESHOLDS}


def test_a_faint_rim_keeps_the_lowest_cut_and_the_cut_is_capped():
    assert calibrate_threshold({0: _soft_person(rim=0.2)}, {0: _truth()})["heldout_best"] == THRESHOLDS[0]
    c = calibrate_threshold({0: _soft_person(rim=0.88)}, {0: _truth()})
    assert c["heldout_best"] == 0.9 and c["synth_threshold"] == MAX_THRESHOLD


def test_nothing_to_calibrate_on_gives_none():
    assert calibrate_threshold({}, {}) is None
    assert calibrate_threshold({0: _soft_person()}, {0: []}) is None  # an empty label file
    tiny = [MaskBox(0, 10, 10, 13, 20, 0, 1.0)]  # 3 px wide: below the 6 px the scoring needs
    assert calibrate_threshold({0: _soft_person()}, {0: tiny}) is None


def test_empty_and_nan_masks_score_zero_not_nan():
    empty = np.stack([np.ones((40, 40), np.float32), np.zeros((40, 40), np.float32)], axis=-1)
    c = calibrate_threshold({0: empty}, {0: _truth()})
    assert c["heldout_best"] == THRESHOLDS[0] and all(v == 0.0 for v in c["box_iou"].values())
    c = calibrate_threshold({0: _soft_person(rim=0.7, nan_at=(16, 14))}, {0: _truth()})
    assert all(np.isfinite(v) for v in c["box_iou"].values())
    assert c["heldout_best"] == 0.75


def test_calibrated_threshold_reads_fit_json_and_survives_bad_files(tmp_path, caplog):
    ck = tmp_path / "static.pt"
    assert calibrated_threshold(ck) is None  # no fit.json
    (tmp_path / "fit.json").write_text("{trunc")
    assert calibrated_threshold(ck) is None and "unreadable" in caplog.text
    (tmp_path / "fit.json").write_text(json.dumps({"heldout": {"mask_threshold": None}}))
    assert calibrated_threshold(ck) is None
    (tmp_path / "fit.json").write_text(json.dumps({"heldout": {"mask_threshold": {"synth_threshold": 0.7}}}))
    assert calibrated_threshold(ck) == 0.7


def test_fit_writes_the_calibration_and_synth_uses_it(tmp_path, tiny_flight):
    flight = tmp_path / "f"
    shutil.copytree(tiny_flight, flight)
    assert main(["fit", str(flight), "--kind", "static", "--iters", "20", "--budget-s", "0", "--samples", "16",
                 "--batch-rays", "256", "--budget-mb", "1", "--threads", "1"]) == 0
    fit_json = flight / "derived" / "fields" / "fit.json"
    info = json.loads(fit_json.read_text())
    assert "mask_threshold" in info["heldout"]  # None when the held-out frame has no person >= 6 px
    info["heldout"]["mask_threshold"] = {"heldout_best": 0.55, "synth_threshold": 0.65}
    fit_json.write_text(json.dumps(info))
    s = synthesize_flight(flight, altitudes_m=(20.0,), count=1, max_outside_fraction=1.0)
    assert s["mask_threshold"] == 0.65 and s["mask_threshold_source"] == "fit.json"
    s = synthesize_flight(flight, altitudes_m=(20.0,), count=1, max_outside_fraction=1.0, mask_threshold=0.5)
    assert s["mask_threshold"] == 0.5 and s["mask_threshold_source"] == "option"
    fit_json.unlink()
    s = synthesize_flight(flight, altitudes_m=(20.0,), count=1, max_outside_fraction=1.0)
    assert s["mask_threshold"] == 0.6 and s["mask_threshold_source"] == "default"
