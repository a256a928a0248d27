"""Real / Synthetic / R+S YOLO datasets: layout, split, count matching, bad labels."""

import pytest

from export.paper_datasets import (
    build_paper_datasets,
    labelled_samples,
    read_class_names,
    split_real,
    write_dataset,
)


def _make(dir_, n, prefix, labels=True):
    (dir_ / "images").mkdir(parents=True)
    (dir_ / "labels").mkdir()
    for i in range(n):
        (dir_ / "images" / f"{prefix}{i:03d}.jpg").write_bytes(b"\xff\xd8fake")
        if labels and i % 2 == 0:
            (dir_ / "labels" / f"{prefix}{i:03d}.txt").write_text("1 0.5 0.5 0.1 0.2\n")
    return labelled_samples(dir_ / "images", dir_ / "labels")


def test_paper_datasets_layout_split_and_matching(tmp_path):
    real = _make(tmp_path / "flight", 10, "f")
    syn = _make(tmp_path / "synth", 30, "s")
    out = build_paper_datasets(real, syn, tmp_path / "ds", ["standing", "kneeling", "prone"], val_every=5)
    assert set(out) == {"real", "synthetic", "r+s"}
    for name, yaml in out.items():
        text = yaml.read_text()
        assert "train: images/train" in text and "  2: prone" in text
        val = sorted(p.name for p in (yaml.parent / "images" / "val").iterdir())
        assert val == ["f004.jpg", "f009.jpg"]  # the same held-out real frames for every set
        n_train = len(list((yaml.parent / "images" / "train").iterdir()))
        assert n_train == {"real": 8, "synthetic": 8, "r+s": 16}[name]
        assert len(list((yaml.parent / "labels" / "train").iterdir())) == n_train
    # frames without a label file become empty label files (background)
    assert (tmp_path / "ds" / "real" / "labels" / "train" / "f001.txt").read_text() == ""


def test_no_synthetic_gives_only_real(tmp_path):
    out = build_paper_datasets(_make(tmp_path / "f", 6, "f"), [], tmp_path / "ds", ["a", "b"])
    assert set(out) == {"real"}


def test_bad_label_and_duplicate_names_are_clear_errors(tmp_path):
    real = _make(tmp_path / "flight", 4, "f")
    (tmp_path / "flight" / "labels" / "f000.txt").write_text("7 0.5 0.5 0.1 0.1\n")
    with pytest.raises(ValueError, match="class < 3"):
        write_dataset(tmp_path / "ds", real, [], ["a", "b", "c"])
    with pytest.raises(ValueError, match="two images"):
        write_dataset(tmp_path / "ds2", real[1:2] + real[1:2], [], ["a", "b", "c"])
    with pytest.raises(ValueError, match="val_every"):
        split_real(real, 1)
    with pytest.raises(ValueError, match="no real frames"):
        build_paper_datasets([], real, tmp_path / "x", ["a"])


def test_class_names(tmp_path):
    assert read_class_names(None) == ["standing", "kneeling", "prone"]
    (tmp_path / "classes.txt").write_text("person\n\ncar\n")
    assert read_class_names(tmp_path / "classes.txt") == ["person", "car"]
