"""How many walking people can K-Planes hold at once? A 2D+t fit of the encoding alone, no rendering.

Question (bench/RESULTS.md, Table III sessions 29-30): both kinds fit the people of the dynamic bench flights
poorly, even on their training frames. Is that the planes (every feature channel is a product of an xt and
a yt plane, so at one instant each channel is a separable x-times-y pattern) or the rest of the fit (poses,
rendering, sampling)? Here the stock encoding (:class:`fields.kplanes.KPlanesEncoding`, 16 features by default,
64/128/256 cells over 40 m, T = 40) and a 64-wide MLP (by default) fit colour and occupancy of ``N`` people directly:
discs of radius 0.3 m with their own colour, walking straight at 1.3 m/s, on a grey ground, at z fixed,
at 40 instants 0.4 s apart on the time grid (the 80-frame flight's training frames). Each batch is 4096
points: a quarter within 1 m of a person (``--near-div`` divides that share: one person given the samples
one of N would get), the rest uniform. The regularisers and the learning-rate schedule are the dynamic
fit's defaults (:class:`fields.dynamic_training.DynamicFitConfig`: TV 2e-4, time smoothness 1e-3, time L1 1e-4;
lr 1e-2 decaying to 1e-3); Adam's betas are torch's defaults, not the fit's (0.9, 0.99).

Reported per N: colour PSNR on a 5 cm grid over 1.2 m squares around each person at every fourth
training instant, and the IoU of occupancy > 0.5 there; the same halfway to the next instant
(``between_*``: never trained on, like the dynamic bench's held-out frames).

    python bench/kplanes_capacity.py --people 1,4,16 [--steps 1500] [--near-div 4] [--one-at-a-time]
        [--features 16] [--hidden 64] [--reg-scale 1] [--xyt-hash LOG2] [--flight-times] [--same-colour]
        --json OUT
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402
from torch import nn  # noqa: E402

from bench._common import write_json  # noqa: E402
from fields.dynamic_training import DynamicFitConfig, regularisers  # noqa: E402
from fields.encodings import HashGrid, HashGridConfig, geometric_resolutions  # noqa: E402
from fields.kplanes import KPlanesConfig, KPlanesEncoding  # noqa: E402

RADIUS_M = 0.3
SIDE_M = 40.0
INSTANTS = 40
DT_S = 0.4
GROUND_RGB = 0.45
#: the dynamic fit's defaults: learning-rate schedule and regulariser weights come from here
FIT = DynamicFitConfig()
SPEED_M_S = 1.3
#: path midpoints within this many metres of the centre per axis: 7 + 10.1 (half a walk) + 0.3 < 20
MID_M = 7.0


def walkers(n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Start positions (n, 2) m, velocities (n, 2) m/s, colours (n, 3).

    Each path's midpoint lies within 7 m of the centre (per axis), so the whole 20 m walk stays inside the
    40 m square: a point outside it would be clamped to the encoding's border and could not be fitted.
    """
    mid = (torch.rand(n, 2, generator=g) - 0.5) * 2 * MID_M
    ang = torch.rand(n, generator=g) * 2 * math.pi
    v = SPEED_M_S * torch.stack([ang.cos(), ang.sin()], 1)
    p0 = mid - v * (INSTANTS - 1) * DT_S / 2
    return p0, v, torch.rand(n, 3, generator=g) * 0.8 + 0.1


def present(instant: torch.Tensor, n: int, one_at_a_time: bool) -> torch.Tensor:
    """(B, n) bool: person j is in the scene at that instant (all, or each for its own run of instants);
    a fractional instant counts as the one before it."""
    if not one_at_a_time:
        return torch.ones(len(instant), n, dtype=torch.bool)
    return (instant.floor().long() * n // INSTANTS)[:, None] == torch.arange(n)[None]


def truth(xy: torch.Tensor, instant: torch.Tensor, people: tuple, one_at_a_time: bool) -> torch.Tensor:
    """(B, 4): RGB and occupancy at ground points ``xy`` (B, 2) m at time indices ``instant`` (B,), which may
    be fractional (between two instants of the time grid)."""
    p0, v, colour = people
    pos = p0[None] + v[None] * (instant.float() * DT_S)[:, None, None]
    dist = (xy[:, None] - pos).norm(dim=-1)
    inside = (dist < RADIUS_M) & present(instant, len(p0), one_at_a_time)
    occ = inside.any(1)
    nearest = torch.where(inside, -dist, torch.full_like(dist, -1e9)).argmax(1)
    rgb = torch.where(occ[:, None], colour[nearest], torch.full((len(xy), 3), GROUND_RGB))
    return torch.cat([rgb, occ[:, None].float()], 1)


def fit_and_score(n: int, steps: int, near_div: int, one_at_a_time: bool, seed: int, features: int = 16,
                  hidden: int = 64, reg_scale: float = 1.0, xyt_hash_log2: int = 0,
                  flight_times: bool = False, same_colour: bool = False) -> dict:
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    people = walkers(n, g)
    if same_colour:  # every walker wears the first one's colour: is telling them apart the hard part?
        people = (people[0], people[1], people[2][:1].expand(n, 3).clone())
    p0, v, _ = people
    enc = KPlanesEncoding(KPlanesConfig(base_resolution=(64, 64, 16), multipliers=(1, 2, 4),
                                        time_resolution=INSTANTS, features=features))
    # optional: a hash grid over (x, y, t) beside the planes, its features concatenated to theirs
    xyt = None
    if xyt_hash_log2:
        levels = geometric_resolutions((16, 16, 8), (256, 256, INSTANTS - 1), 8)
        xyt = HashGrid(HashGridConfig(resolutions=levels, features=2, log2_table=xyt_hash_log2))
    extra = xyt.out_dim if xyt is not None else 0
    mlp = nn.Sequential(nn.Linear(enc.out_dim + extra, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                        nn.Linear(hidden, 4))
    extra_params = list(xyt.parameters()) if xyt is not None else []
    opt = torch.optim.Adam([*enc.parameters(), *mlp.parameters(), *extra_params], lr=FIT.lr, eps=1e-15)

    def predict(xy: torch.Tensor, instant: torch.Tensor) -> torch.Tensor:
        x01 = torch.cat([xy / SIDE_M + 0.5, torch.full((len(xy), 1), 0.05)], 1)
        # on the grid: instant i at row i; as the flight: training frame 2i of 2 * INSTANTS at t01 = 2i / (2N - 1)
        t01 = instant.float() * (2.0 / (2 * INSTANTS - 1) if flight_times else 1.0 / (INSTANTS - 1))
        feats = enc(x01, t01)["features"]
        if xyt is not None:
            feats = torch.cat([feats, xyt(torch.cat([x01[:, :2], t01[:, None]], 1))], 1)
        return mlp(feats)

    batch, near = 4096, 4096 // 4 // near_div
    t0 = time.perf_counter()
    for step in range(steps):
        for group in opt.param_groups:
            group["lr"] = FIT.lr * FIT.lr_final ** (step / steps)
        instant = torch.randint(INSTANTS, (batch,), generator=g)
        xy = (torch.rand(batch, 2, generator=g) - 0.5) * SIDE_M
        who = instant[:near] * n // INSTANTS if one_at_a_time else torch.randint(n, (near,), generator=g)
        jitter = (torch.rand(near, 2, generator=g) - 0.5) * 2.0  # within 1 m of the person, per axis
        xy[:near] = p0[who] + v[who] * (instant[:near].float() * DT_S)[:, None] + jitter
        loss = ((predict(xy, instant) - truth(xy, instant, people, one_at_a_time)) ** 2).mean()
        loss = loss + reg_scale * regularisers(enc, FIT)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    train_s = time.perf_counter() - t0

    on_rows = score(predict, people, one_at_a_time, 0.0)
    between = score(predict, people, one_at_a_time, 0.5)
    return {"people": n, "steps": steps, "near_div": near_div, "one_at_a_time": one_at_a_time, "seed": seed,
            "features": features, "hidden": hidden, "reg_scale": reg_scale, "xyt_hash_log2": xyt_hash_log2,
            "flight_times": flight_times, "same_colour": same_colour,
            "train_s": round(train_s, 1), "colour_psnr_db": on_rows[0], "occupancy_iou": on_rows[1],
            "between_colour_psnr_db": between[0], "between_occupancy_iou": between[1]}


def score(predict, people: tuple, one_at_a_time: bool, offset: float) -> tuple[float, float]:
    """Colour PSNR (dB) and occupancy IoU on 1.2 m squares (5 cm grid) around each person present at every
    fourth instant plus ``offset`` (0: the training instants; 0.5: halfway to the next, never trained on,
    as the dynamic bench's held-out frames)."""
    p0, v, _ = people
    n = len(p0)
    side = torch.linspace(-0.6, 0.6, 25)
    offsets = torch.stack(torch.meshgrid(side, side, indexing="ij"), -1).reshape(-1, 2)
    sq_err, count, inter, union = 0.0, 0, 0, 0
    with torch.no_grad():
        for i in range(0, INSTANTS - 1, 4):
            for j in range(n):
                if one_at_a_time and i * n // INSTANTS != j:
                    continue
                xy = p0[j] + v[j] * (i + offset) * DT_S + offsets
                instant = torch.full((len(xy),), i + offset)
                out, want = predict(xy, instant), truth(xy, instant, people, one_at_a_time)
                sq_err += float(((out[:, :3] - want[:, :3]) ** 2).sum())
                count += out[:, :3].numel()
                a, b = out[:, 3] > 0.5, want[:, 3] > 0.5
                inter, union = inter + int((a & b).sum()), union + int((a | b).sum())
    return round(-10 * math.log10(sq_err / count), 2), round(inter / max(union, 1), 3)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--people", default="1,4,16", help="comma-separated numbers of walkers")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--near-div", type=int, default=1, help="divide the near-people share of a batch by this")
    ap.add_argument("--one-at-a-time", action="store_true", help="each person walks alone, in turn")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--features", type=int, default=16, help="features per plane (the dynamic fit's default)")
    ap.add_argument("--hidden", type=int, default=64, help="width of the decoder MLP")
    ap.add_argument("--reg-scale", type=float, default=1.0, help="multiply the three regularisers by this")
    ap.add_argument("--xyt-hash", type=int, default=0, metavar="LOG2",
                    help="add a hash grid over (x, y, t) with 2**LOG2 entries per level (0: planes only)")
    ap.add_argument("--flight-times", action="store_true",
                    help="time the instants as the dynamic fit does (training frames of twice as many, "
                         "normalised over all): they drift off the time grid's rows by up to half a row")
    ap.add_argument("--same-colour", action="store_true", help="every walker the same colour")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = []
    for n in (int(a) for a in args.people.split(",")):
        rows.append(fit_and_score(n, args.steps, args.near_div, args.one_at_a_time, args.seed, args.features,
                                  args.hidden, args.reg_scale, args.xyt_hash, args.flight_times,
                                  args.same_colour))
        print(rows[-1], flush=True)
    write_json("kplanes_capacity", {"threads": args.threads, "rows": rows}, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
