"""YOLOv8 detection loss: task-aligned assignment, then CIoU + DFL box losses and BCE class loss.

All boxes are x0, y0, x1, y1. The assigner works in input pixels; the box losses in grid units
of each anchor's stride (which is what the DFL bins measure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from export.yolo import bbox2dist, dist2bbox, make_anchors


def bbox_iou(box1: torch.Tensor, box2: torch.Tensor, ciou: bool = False, eps: float = 1e-7) -> torch.Tensor:
    """IoU (or CIoU) of x0y0x1y1 boxes broadcast along the leading dims; last dim 4 → result [..., 1]."""
    b1_x1, b1_y1, b1_x2, b1_y2 = box1.chunk(4, -1)
    b2_x1, b2_y1, b2_x2, b2_y2 = box2.chunk(4, -1)
    w1, h1 = b1_x2 - b1_x1, (b1_y2 - b1_y1).clamp(eps)
    w2, h2 = b2_x2 - b2_x1, (b2_y2 - b2_y1).clamp(eps)
    inter = (b1_x2.minimum(b2_x2) - b1_x1.maximum(b2_x1)).clamp(0) * \
            (b1_y2.minimum(b2_y2) - b1_y1.maximum(b2_y1)).clamp(0)
    union = w1 * h1 + w2 * h2 - inter + eps
    iou = inter / union
    if not ciou:
        return iou
    cw = b1_x2.maximum(b2_x2) - b1_x1.minimum(b2_x1)
    ch = b1_y2.maximum(b2_y2) - b1_y1.minimum(b2_y1)
    c2 = cw.pow(2) + ch.pow(2) + eps  # squared diagonal of the enclosing box
    rho2 = ((b2_x1 + b2_x2 - b1_x1 - b1_x2).pow(2) + (b2_y1 + b2_y2 - b1_y1 - b1_y2).pow(2)) / 4
    v = (4 / math.pi**2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)).pow(2)
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)


class TaskAlignedAssigner(nn.Module):
    """Assign each ground-truth box its ``topk`` anchors by ``score^alpha · IoU^beta`` (TOOD).

    Candidates must have their centre inside the box; an anchor claimed by several boxes goes to
    the one it overlaps most. Target scores are the IoU-normalised alignment metric.
    """

    def __init__(self, topk: int = 10, num_classes: int = 80, alpha: float = 0.5, beta: float = 6.0,
                 eps: float = 1e-9):
        super().__init__()
        self.topk, self.nc, self.alpha, self.beta, self.eps = topk, num_classes, alpha, beta, eps

    @torch.no_grad()
    def forward(self, pd_scores, pd_bboxes, anc_points, gt_labels, gt_bboxes, mask_gt):
        """pd_scores [B,A,C] (sigmoid), pd_bboxes [B,A,4] px, anc_points [A,2] px, gt_labels [B,M,1],
        gt_bboxes [B,M,4] px, mask_gt [B,M,1] → (labels [B,A], bboxes [B,A,4], scores [B,A,C], fg [B,A])."""
        b, a, _ = pd_scores.shape
        m = gt_bboxes.shape[1]
        device = pd_scores.device
        if m == 0:
            return (torch.full((b, a), self.nc, device=device), torch.zeros_like(pd_bboxes),
                    torch.zeros_like(pd_scores), torch.zeros((b, a), dtype=torch.bool, device=device))
        # centre-in-box candidates [B,M,A]
        lt = anc_points[None, None] - gt_bboxes[:, :, None, :2]
        rb = gt_bboxes[:, :, None, 2:] - anc_points[None, None]
        mask_in = (torch.cat((lt, rb), -1).amin(-1) > self.eps).to(pd_scores.dtype)
        mask = mask_in * mask_gt
        # alignment metric [B,M,A]
        ind_b = torch.arange(b, device=device).view(-1, 1).expand(-1, m)
        scores = pd_scores[ind_b, :, gt_labels.squeeze(-1).long()]  # [B,M,A]
        overlaps = bbox_iou(gt_bboxes[:, :, None], pd_bboxes[:, None], ciou=True).squeeze(-1).clamp_(0)
        overlaps = overlaps * mask
        align = scores.pow(self.alpha) * overlaps.pow(self.beta) * mask
        # top-k per gt
        k = min(self.topk, a)
        top_idx = align.topk(k, dim=-1).indices  # [B,M,k]
        mask_topk = torch.zeros_like(align).scatter_(-1, top_idx, 1.0)
        mask_pos = mask_topk * mask
        # resolve anchors claimed by several gts: keep the highest overlap
        fg = mask_pos.sum(-2)  # [B,A]
        if fg.max() > 1:
            multi = (fg.unsqueeze(1) > 1).expand(-1, m, -1)
            best = F.one_hot(overlaps.argmax(1), m).permute(0, 2, 1).to(overlaps.dtype)
            mask_pos = torch.where(multi, best, mask_pos)
            fg = mask_pos.sum(-2)
        target_gt_idx = mask_pos.argmax(-2)  # [B,A]
        fg_mask = fg > 0
        # targets
        flat_idx = target_gt_idx + torch.arange(b, device=device)[:, None] * m
        t_labels = gt_labels.long().flatten()[flat_idx].clamp_(0)  # [B,A]
        t_bboxes = gt_bboxes.view(-1, 4)[flat_idx]
        t_scores = F.one_hot(t_labels, self.nc).to(pd_scores.dtype) * fg_mask[..., None]
        align = align * mask_pos
        pos_align = align.amax(-1, keepdim=True)
        pos_over = (overlaps * mask_pos).amax(-1, keepdim=True)
        norm = (align * pos_over / (pos_align + self.eps)).amax(-2).unsqueeze(-1)  # [B,A,1]
        return t_labels, t_bboxes, t_scores * norm, fg_mask


@dataclass
class LossGains:
    """Loss weights of the published recipe."""

    box: float = 7.5
    cls: float = 0.5
    dfl: float = 1.5


class DetectionLoss:
    """Loss of a :class:`export.yolo.YOLOv8` in train mode; ``__call__(feats, targets) → (total, items[3])``.

    ``targets``: [M,6] rows (image index in batch, class, x0, y0, x1, y1) in input pixels. ``total`` is
    scaled by the batch size (the published convention the learning rates are tuned for).
    """

    def __init__(self, model, gains: LossGains | None = None, topk: int = 10):
        head = model.model[-1]
        self.nc, self.reg_max = head.nc, head.reg_max
        self.no = head.no
        self.strides = head.stride.tolist()
        self.gains = gains or LossGains()
        self.assigner = TaskAlignedAssigner(topk=topk, num_classes=self.nc)
        self.proj = torch.arange(self.reg_max, dtype=torch.float32)

    def _targets(self, targets: torch.Tensor, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """[M,6] → padded [B,Mmax,5] (class, box) and mask [B,Mmax,1]."""
        counts = torch.bincount(targets[:, 0].long(), minlength=batch) if len(targets) else torch.zeros(batch)
        mmax = int(counts.max().item()) if len(targets) else 0
        out = torch.zeros(batch, mmax, 5, device=targets.device)
        mask = torch.zeros(batch, mmax, 1, device=targets.device)
        for i in range(batch):
            sel = targets[targets[:, 0] == i]
            out[i, : len(sel)] = sel[:, 1:]
            mask[i, : len(sel)] = 1
        return out, mask

    def __call__(self, feats: list[torch.Tensor], targets: torch.Tensor):
        b = feats[0].shape[0]
        dtype, device = feats[0].dtype, feats[0].device
        x = torch.cat([f.view(b, self.no, -1) for f in feats], 2)
        pred_distri, pred_scores = x.split((4 * self.reg_max, self.nc), 1)
        pred_distri = pred_distri.permute(0, 2, 1).contiguous()  # [B,A,4*R]
        pred_scores = pred_scores.permute(0, 2, 1).contiguous()  # [B,A,C]
        shapes = [(f.shape[2], f.shape[3]) for f in feats]
        anchors, stride = make_anchors(shapes, self.strides, dtype, device)
        gt, mask_gt = self._targets(targets.to(device), b)
        gt_labels, gt_bboxes = gt[..., :1], gt[..., 1:]

        a = pred_distri.shape[1]
        proba = pred_distri.view(b, a, 4, self.reg_max).softmax(3)
        pred_bboxes = dist2bbox(proba @ self.proj.to(device, dtype), anchors, xywh=False)  # grid units

        t_labels, t_bboxes, t_scores, fg = self.assigner(
            pred_scores.detach().sigmoid(), (pred_bboxes.detach() * stride).to(gt_bboxes.dtype),
            anchors * stride, gt_labels, gt_bboxes, mask_gt)
        t_sum = max(t_scores.sum(), 1.0)

        loss_cls = F.binary_cross_entropy_with_logits(pred_scores, t_scores.to(dtype), reduction="sum") / t_sum
        loss_box = torch.zeros((), device=device)
        loss_dfl = torch.zeros((), device=device)
        if fg.any():
            t_bboxes = t_bboxes / stride
            weight = t_scores.sum(-1)[fg].unsqueeze(-1)
            iou = bbox_iou(pred_bboxes[fg], t_bboxes[fg], ciou=True)
            loss_box = ((1.0 - iou) * weight).sum() / t_sum
            t_ltrb = bbox2dist(anchors, t_bboxes, self.reg_max)[fg]  # [P,4] in [0, reg_max-1)
            loss_dfl = (self._dfl(pred_distri[fg].view(-1, self.reg_max), t_ltrb) * weight).sum() / t_sum
        items = torch.stack((loss_box * self.gains.box, loss_cls * self.gains.cls, loss_dfl * self.gains.dfl))
        return items.sum() * b, items.detach()

    def _dfl(self, logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Distribution focal loss: cross-entropy to the two bins around each continuous target; [P,1]."""
        tl = target.long()
        tr = tl + 1
        wl = tr - target
        wr = 1 - wl
        ce_l = F.cross_entropy(logits, tl.view(-1), reduction="none").view(tl.shape)
        ce_r = F.cross_entropy(logits, tr.view(-1), reduction="none").view(tl.shape)
        return (ce_l * wl + ce_r * wr).mean(-1, keepdim=True)
