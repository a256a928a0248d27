"""Loss pieces: IoU/CIoU on hard numbers, the task-aligned assigner, finite loss on edge cases."""

import math

import torch

from export.loss import DetectionLoss, TaskAlignedAssigner, bbox_iou
from export.yolo import YOLOv8


def test_iou_known_values():
    a = torch.tensor([[0.0, 0, 10, 10]])
    assert bbox_iou(a, a).item() == 1.0 - 0.0 or abs(bbox_iou(a, a).item() - 1) < 1e-6
    b = torch.tensor([[5.0, 0, 15, 10]])
    assert abs(bbox_iou(a, b).item() - 50 / 150) < 1e-6
    assert bbox_iou(a, torch.tensor([[20.0, 20, 30, 30]])).item() == 0.0


def test_ciou_penalises_distance_and_aspect():
    a = torch.tensor([[0.0, 0, 10, 10]])
    assert abs(bbox_iou(a, a, ciou=True).item() - 1) < 1e-5
    far = torch.tensor([[20.0, 0, 30, 10]])
    # disjoint: IoU 0, centre distance 20, enclosing diagonal² 30² + 10²
    assert abs(bbox_iou(a, far, ciou=True).item() - (-(400 / 1000))) < 1e-4
    thin = torch.tensor([[0.0, 0, 10, 5]])
    assert bbox_iou(a, thin, ciou=True).item() < bbox_iou(a, thin).item()


def test_assigner_picks_anchors_inside_the_box():
    anchors = torch.tensor([[4.0, 4], [12, 4], [4, 12], [12, 12], [28, 28]])
    gt = torch.tensor([[[0.0, 0, 16, 16]]])
    pd_boxes = gt.expand(1, 5, 4).clone()
    pd_scores = torch.full((1, 5, 2), 0.5)
    labels, boxes, scores, fg = TaskAlignedAssigner(topk=10, num_classes=2)(
        pd_scores, pd_boxes, anchors, torch.tensor([[[1.0]]]), gt, torch.ones(1, 1, 1))
    assert fg.tolist() == [[True, True, True, True, False]]
    assert labels[0, :4].tolist() == [1, 1, 1, 1]
    assert torch.allclose(scores[0, :4, 1], torch.ones(4)) and scores[0, :, 0].abs().sum() == 0


def test_assigner_topk_limits_positives():
    anchors = torch.stack(torch.meshgrid(torch.arange(8.0) + 0.5, torch.arange(8.0) + 0.5, indexing="xy"), -1)
    anchors = anchors.reshape(-1, 2)
    gt = torch.tensor([[[0.0, 0, 8, 8]]])
    pd = torch.rand(1, 64, 4) * 4 + torch.tensor([0.0, 0, 4, 4])
    _, _, _, fg = TaskAlignedAssigner(topk=5, num_classes=1)(
        torch.rand(1, 64, 1), pd, anchors, torch.zeros(1, 1, 1), gt, torch.ones(1, 1, 1))
    assert fg.sum() == 5


def test_loss_is_finite_with_and_without_targets_and_backpropagates():
    torch.manual_seed(0)
    model = YOLOv8(nc=2).train()
    loss_fn = DetectionLoss(model)
    x = torch.rand(2, 3, 64, 64)
    targets = torch.tensor([[0, 1, 10.0, 10, 30, 40], [1, 0, 0.0, 0, 3, 3], [1, 1, 60, 50, 64, 64]])
    for t in (targets, torch.zeros(0, 6)):
        model.zero_grad()
        loss, items = loss_fn(model(x), t)
        assert math.isfinite(loss.item()) and items.shape == (3,)
        loss.backward()
        g = model.model[0].conv.weight.grad
        assert g is not None and torch.isfinite(g).all()
    assert items[0] == 0 and items[2] == 0  # no targets: only the class loss


def test_a_few_steps_reduce_the_loss_on_one_batch():
    torch.manual_seed(0)
    model = YOLOv8(nc=1).train()
    loss_fn = DetectionLoss(model)
    x = torch.rand(2, 3, 64, 64)
    t = torch.tensor([[0, 0, 8.0, 8, 40, 40], [1, 0, 20.0, 30, 50, 60]])
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    losses = []
    for _ in range(6):
        opt.zero_grad()
        loss, _ = loss_fn(model(x), t)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]
