"""The model: ultralytics-identical parameter counts and state-dict keys, output layout."""

import pytest
import torch

from export.yolo import YOLOv8, count_parameters, make_anchors


@pytest.mark.parametrize("nc, expected", [(1, 3_011_043), (80, 3_157_200)])
def test_parameter_count_matches_ultralytics_yolov8n(nc, expected):
    assert count_parameters(YOLOv8(nc=nc)) == expected


def test_state_dict_keys_follow_ultralytics_layout():
    keys = list(YOLOv8(nc=1).state_dict())
    assert keys[:6] == ["model.0.conv.weight", "model.0.bn.weight", "model.0.bn.bias", "model.0.bn.running_mean",
                        "model.0.bn.running_var", "model.0.bn.num_batches_tracked"]
    for k in ["model.2.cv1.conv.weight", "model.2.m.0.cv2.bn.bias", "model.4.m.1.cv1.conv.weight",
              "model.9.cv2.conv.weight", "model.21.cv2.bn.running_var", "model.22.cv2.0.0.conv.weight",
              "model.22.cv2.2.2.bias", "model.22.cv3.1.2.weight"]:
        assert k in keys
    assert keys[-1] == "model.22.dfl.conv.weight"
    assert not any(k.startswith(("model.10.", "model.11.", "model.13.", "model.14.")) for k in keys)
    # 1 weight layer keys per module index: 23 layers, parameterless 10, 11, 13, 14, 17, 20
    assert {int(k.split(".")[1]) for k in keys} == set(range(23)) - {10, 11, 13, 14, 17, 20}


def test_state_dict_round_trips_strictly_between_instances():
    a, b = YOLOv8(nc=2), YOLOv8(nc=2)
    b.load_state_dict(a.state_dict(), strict=True)
    with pytest.raises(RuntimeError):
        YOLOv8(nc=3).load_state_dict(a.state_dict(), strict=True)


def test_small_scale_is_wider():
    assert count_parameters(YOLOv8(nc=80, scale="s")) == 11_166_560


def test_eval_output_layout_non_square():
    model = YOLOv8(nc=3).eval()
    with torch.no_grad():
        out = model(torch.rand(2, 3, 64, 96))
    n = sum((64 // s) * (96 // s) for s in (8, 16, 32))
    assert out.shape == (2, 7, n)
    scores = out[:, 4:]
    assert (scores >= 0).all() and (scores <= 1).all()
    # boxes centred on their anchors at init (uniform DFL → equal distances on each side)
    anchors, strides = make_anchors([(8, 12), (4, 6), (2, 3)], (8, 16, 32), torch.float32, "cpu")
    assert torch.allclose(out[0, :2].T, anchors * strides, atol=1e-3)


def test_train_output_is_raw_maps():
    model = YOLOv8(nc=1).train()
    feats = model(torch.rand(1, 3, 64, 64))
    assert [tuple(f.shape) for f in feats] == [(1, 65, 8, 8), (1, 65, 4, 4), (1, 65, 2, 2)]


def test_bad_arguments():
    with pytest.raises(ValueError):
        YOLOv8(nc=0)
    with pytest.raises(ValueError):
        YOLOv8(nc=1, scale="q")
    with pytest.raises(ValueError):
        YOLOv8(nc=2, names={0: "a"})
