"""The base detector: cache location, provenance, leak check, and one tiny end-to-end pretraining."""

import json

import pytest

from agent.replay import resolve_base
from export.pretrain import (
    PretrainConfig,
    base_info,
    check_base_for_world,
    default_base_dir,
    find_base,
    pretrain_base,
    render_data,
)
from export.train import load_checkpoint


def test_cache_location_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("UAVSIM_CACHE", str(tmp_path / "c"))
    assert default_base_dir() == tmp_path / "c" / "detector-base"
    monkeypatch.delenv("UAVSIM_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert default_base_dir() == tmp_path / "x" / "uavsim" / "detector-base"


def test_find_base_and_resolve(monkeypatch, tmp_path):
    monkeypatch.setenv("UAVSIM_CACHE", str(tmp_path))
    assert find_base() is None and resolve_base("auto") is None  # nothing cached: from scratch
    assert resolve_base("none") is None
    with pytest.raises(FileNotFoundError, match="pretrain"):
        find_base(tmp_path / "missing.pt")
    base = default_base_dir()
    base.mkdir(parents=True)
    (base / "base.pt").write_bytes(b"x")
    assert find_base() == base / "base.pt" and find_base(base) == base / "base.pt"
    assert resolve_base("auto") == str(base / "base.pt")


def test_a_base_trained_on_the_flown_world_is_refused(tmp_path):
    (tmp_path / "base.pt").write_bytes(b"x")
    (tmp_path / "base.json").write_text(json.dumps({"world_seeds": [10, 11, 20]}))
    check_base_for_world(tmp_path / "base.pt", 0)
    with pytest.raises(ValueError, match="world 11"):
        check_base_for_world(tmp_path / "base.pt", 11)
    (tmp_path / "base.json").write_text("{not json")
    assert base_info(tmp_path / "base.pt") == {}


def test_overlapping_train_and_val_worlds_are_refused(tmp_path):
    with pytest.raises(ValueError, match="differ"):
        render_data(PretrainConfig(out=str(tmp_path), train_seeds=(1, 2), val_seeds=(2,)))


def test_tiny_pretraining_writes_a_loadable_base(tmp_path):
    cfg = PretrainConfig(out=str(tmp_path), train_seeds=(30,), val_seeds=(31,), train_images=4, val_images=2,
                         width=96, height=64, imgsz=64, epochs=1, batch=2, nbs=2,
                         world_overrides={"texture_size": 512, "texel_m": 0.05, "n_people": 6})
    info = pretrain_base(cfg)
    assert info["world_seeds"] == [30, 31] and info["epochs_run"] == 1
    model, meta = load_checkpoint(tmp_path / "base.pt")
    assert model.nc == 3 and json.loads((tmp_path / "base.json").read_text())["kind"] == "uavsim-detector-base"
