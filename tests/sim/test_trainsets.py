"""Simulator training sets: reproducible, resumable, labelled."""

import pytest

from sim.trainsets import OrbitSetSpec, render_orbit_split, write_data_yaml

SMALL = {"texture_size": 512, "texel_m": 0.05, "n_people": 6}
SPEC = OrbitSetSpec(width=64, height=48, supersample=1)


def test_split_is_reproducible_and_resumable(tmp_path):
    root = tmp_path / "train"
    assert render_orbit_split(root, (3, 4), 3, rng_seed=1, spec=SPEC, world_overrides=SMALL) == 3
    names = sorted(p.stem for p in (root / "labels").iterdir())
    assert names == ["s3_00000", "s3_00001", "s4_00002"]  # ceil(3/2) views per world
    first = (root / "images" / "s4_00002.png").read_bytes()
    (root / "labels" / "s4_00002.txt").unlink()  # an interrupted view: its label is written last
    (root / "images" / "s4_00002.png").write_bytes(b"partial")
    assert render_orbit_split(root, (3, 4), 3, rng_seed=1, spec=SPEC, world_overrides=SMALL) == 1
    assert (root / "images" / "s4_00002.png").read_bytes() == first  # same view parameters when resumed
    for label in (root / "labels").iterdir():
        for line in label.read_text().splitlines():
            cls, *box = line.split()
            assert int(cls) in (0, 1, 2) and all(0.0 <= float(v) <= 1.0 for v in box)


def test_bad_arguments_are_refused(tmp_path):
    with pytest.raises(ValueError, match="world seed"):
        render_orbit_split(tmp_path, (), 3, rng_seed=0, spec=SPEC)
    with pytest.raises(ValueError, match="image"):
        render_orbit_split(tmp_path, (1,), 0, rng_seed=0, spec=SPEC)


def test_data_yaml_lists_both_splits(tmp_path):
    text = write_data_yaml(tmp_path, ["standing", "kneeling"]).read_text()
    assert "train: train/images" in text and "val: val/images" in text and "1: kneeling" in text
