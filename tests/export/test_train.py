"""Training end to end on a tiny drawn dataset; checkpoints; the detector CLI (train → export → eval)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from export.train import TrainConfig, build_optimizer, fine_tune_config, load_checkpoint, train
from export.yolo import YOLOv8

REPO = Path(__file__).resolve().parents[2]


def test_tiny_training_writes_checkpoints_and_history(tiny_data, tmp_path):
    summary = train(TrainConfig(data=str(tiny_data), out=str(tmp_path), epochs=2, batch=4, imgsz=64,
                                close_mosaic=1, threads=1))
    assert [r["epoch"] for r in summary["history"]] == [1, 2]
    for r in summary["history"]:
        assert all(map(lambda v: v == v, (r["box"], r["cls"], r["dfl"])))  # no NaN
        assert 0.0 <= r["map50"] <= 1.0
    model, meta = load_checkpoint(summary["best"])
    assert model.names == {0: "red", 1: "green", 2: "blue"} and meta["imgsz"] == 64
    assert json.loads((tmp_path / "history.json").read_text())[-1]["epoch"] == 2
    # resume from the checkpoint (fine-tuning path)
    again = train(TrainConfig(data=str(tiny_data), out=str(tmp_path / "ft"), weights=summary["last"], epochs=1,
                              batch=6, imgsz=64, threads=1))
    assert Path(again["best"]).is_file()


def test_fine_tuning_a_flight_steps_every_batch(tiny_data, tmp_path):
    """A flight's few images in a few batches: the default nominal batch of 64 gives one optimizer step
    per epoch (the weights barely move from the base); the fine-tuning config steps every batch."""
    common = dict(data=str(tiny_data), epochs=2, batch=2, imgsz=64, close_mosaic=0, threads=1)
    default = train(TrainConfig(out=str(tmp_path / "default"), **common))
    tuned = train(fine_tune_config(out=str(tmp_path / "tuned"), **common))
    assert default["optimizer_steps"] == 2  # 6 training images in 3 batches of 2, one step an epoch
    assert tuned["optimizer_steps"] == 2 * 3
    assert tuned["lr0"] == pytest.approx(0.1 * default["lr0"])  # a tenth of the from-scratch rate
    assert fine_tune_config(batch=8, nbs=64).nbs == 64  # explicit fields win


def test_auto_optimizer_follows_the_recipe():
    model = YOLOv8(nc=3)
    cfg = TrainConfig(batch=16)
    opt, lr, name = build_optimizer(model, cfg, 3, iterations=500)
    assert name == "AdamW" and lr == pytest.approx(0.002 * 5 / 7, abs=1e-6)
    groups = opt.param_groups
    assert groups[0]["weight_decay"] == 0 and groups[2]["weight_decay"] == 0 and groups[1]["weight_decay"] > 0
    n = sum(p.numel() for g in groups for p in g["params"])
    assert n == sum(p.numel() for p in model.parameters() if p.requires_grad)
    _, lr, name = build_optimizer(model, TrainConfig(batch=16), 3, iterations=20000)
    assert name == "SGD" and lr == 0.01


def test_bad_checkpoint_is_a_clear_error(tmp_path):
    bad = tmp_path / "x.pt"
    bad.write_bytes(b"junk")
    with pytest.raises(ValueError, match="cannot read checkpoint"):
        load_checkpoint(bad)
    torch.save({"foo": 1}, bad)
    with pytest.raises(ValueError, match="not a uavsim detector checkpoint"):
        load_checkpoint(bad)
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "none.pt")


def uavsim(*args):
    return subprocess.run([sys.executable, "-m", "agent.cli", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow
def test_cli_train_export_eval(tiny_data, tmp_path):
    out = uavsim("detector", "train", "--data", tiny_data, "--epochs", "1", "--batch", "6", "--imgsz", "64",
                 "--out", tmp_path / "run")
    assert out.returncode == 0, out.stderr
    assert "best" in out.stdout
    out = uavsim("detector", "export", "--weights", tmp_path / "run" / "best.pt", "--out", tmp_path / "m.onnx")
    assert out.returncode == 0, out.stderr
    for model in (tmp_path / "m.onnx", tmp_path / "run" / "best.pt"):
        js = tmp_path / f"{model.suffix}.json"
        out = uavsim("detector", "eval", "--model", model, "--data", tiny_data, "--json", js)
        assert out.returncode == 0, out.stderr
        res = json.loads(js.read_text())
        assert set(res["per_class"]) == {"red", "green", "blue"} and 0 <= res["map50"] <= 1
        assert "mAP50:95" in out.stdout


def test_cli_eval_bad_inputs_are_one_line_errors(tiny_data, tmp_path):
    out = uavsim("detector", "eval", "--model", tmp_path / "m.txt", "--data", tiny_data)
    assert out.returncode == 2 and ".onnx or .pt" in out.stderr
    out = uavsim("detector", "train", "--data", tmp_path / "none.yaml")
    assert out.returncode == 2 and "not found" in out.stderr
