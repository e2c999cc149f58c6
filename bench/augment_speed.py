"""radserve's augmentation kernels vs a PyTorch implementation of the same semantics, same cores.

    make bench-augment            (or: .venv/bin/python bench/augment_speed.py)

Both sides get batches of 512 samples of 3 stacked RGB frames (9x100x100 for crop / translate /
window, 9x84x84 for the rest, DrQ's shift and intensity among them), uniform random bytes, uint8 in and uint8 out, on the same number of
threads. PyTorch is written here from the issue's semantics (per-sample parameters, the same for
every frame of a stack), vectorized over the batch where PyTorch allows it (advanced indexing for
crop/translate, one grouped conv2d for random convolution); it is not RAD's reference code, which is
slower still. Prints ms per batch, GB/s of output, the ratio to a parallel copy of the same output
bytes (measured by radserve in the same run), and the speed-up over PyTorch; a full run (no --filter)
writes bench/results/augment_speed.json, which docs/augmentations.md renders.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

import record  # noqa: E402  (bench/record.py: the results file)

ROOT = Path(__file__).resolve().parent.parent
LUMA = (0.2989, 0.587, 0.114)


def per_sample(x: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """Broadcast a per-sample value over [B, C, H, W]."""
    return value.view(-1, *([1] * (x.dim() - 1)))


def crop(x: torch.Tensor, size: int) -> torch.Tensor:
    b, c, h, w = x.shape
    top = torch.randint(0, h - size + 1, (b,))
    left = torch.randint(0, w - size + 1, (b,))
    span = torch.arange(size)
    rows = (top[:, None] + span)[:, None, :, None]
    cols = (left[:, None] + span)[:, None, None, :]
    return x[torch.arange(b)[:, None, None, None], torch.arange(c)[None, :, None, None], rows, cols]


def center_crop(x: torch.Tensor, size: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    top, left = (h - size) // 2, (w - size) // 2
    return x[..., top : top + size, left : left + size].contiguous()


def translate(x: torch.Tensor, size: int) -> torch.Tensor:
    b, c, h, w = x.shape
    out = torch.zeros((b, c, size, size), dtype=x.dtype)
    top = torch.randint(0, size - h + 1, (b,))
    left = torch.randint(0, size - w + 1, (b,))
    rows = (top[:, None] + torch.arange(h))[:, None, :, None]
    cols = (left[:, None] + torch.arange(w))[:, None, None, :]
    out[torch.arange(b)[:, None, None, None], torch.arange(c)[None, :, None, None], rows, cols] = x
    return out


def window(x: torch.Tensor, size: int) -> torch.Tensor:
    b, _, h, w = x.shape
    top = torch.randint(0, h - size + 1, (b,))
    left = torch.randint(0, w - size + 1, (b,))
    ys, xs = torch.arange(h), torch.arange(w)
    keep_rows = (ys[None, :] >= top[:, None]) & (ys[None, :] < (top + size)[:, None])
    keep_cols = (xs[None, :] >= left[:, None]) & (xs[None, :] < (left + size)[:, None])
    mask = keep_rows[:, None, :, None] & keep_cols[:, None, None, :]
    return x * mask


def flip(x: torch.Tensor, p: float) -> torch.Tensor:
    fire = torch.rand(x.shape[0]) < p
    return torch.where(per_sample(x, fire), x.flip(3), x)


def rotate(x: torch.Tensor, p: float) -> torch.Tensor:
    b = x.shape[0]
    quarters = torch.where(torch.rand(b) < p, torch.randint(1, 4, (b,)), torch.zeros(b, dtype=torch.long))
    out = x.clone()
    for k in (1, 2, 3):
        chosen = quarters == k
        out[chosen] = torch.rot90(x[chosen], k, (2, 3))
    return out


def luma(frames: torch.Tensor) -> torch.Tensor:
    """[..., 3, H, W] float -> [..., 1, H, W]."""
    return LUMA[0] * frames[..., 0:1, :, :] + LUMA[1] * frames[..., 1:2, :, :] + LUMA[2] * frames[..., 2:3, :, :]


def grayscale(x: torch.Tensor, p: float) -> torch.Tensor:
    b, c, h, w = x.shape
    frames = x.view(b, c // 3, 3, h, w).float()
    gray = luma(frames).round().clamp(0, 255).to(torch.uint8).expand(-1, -1, 3, -1, -1).reshape(b, c, h, w)
    fire = torch.rand(b) < p
    return torch.where(per_sample(x, fire), gray, x)


def cutout(x: torch.Tensor, low: int, high: int, colour: bool) -> torch.Tensor:
    b, c, h, w = x.shape
    rect_h = torch.randint(low, high + 1, (b,))
    rect_w = torch.randint(low, high + 1, (b,))
    top = (torch.rand(b) * (h - rect_h + 1)).long()
    left = (torch.rand(b) * (w - rect_w + 1)).long()
    ys, xs = torch.arange(h), torch.arange(w)
    in_rows = (ys[None, :] >= top[:, None]) & (ys[None, :] < (top + rect_h)[:, None])
    in_cols = (xs[None, :] >= left[:, None]) & (xs[None, :] < (left + rect_w)[:, None])
    mask = (in_rows[:, None, :, None] & in_cols[:, None, None, :])
    if not colour:
        return x.masked_fill(mask, 0)
    fill = torch.randint(0, 256, (b, 1, 3, 1, 1), dtype=torch.uint8).expand(-1, c // 3, -1, -1, -1).reshape(b, c, 1, 1)
    return torch.where(mask, fill, x)


def random_conv(x: torch.Tensor) -> torch.Tensor:
    """One grouped conv2d: every frame of sample i uses sample i's 3x3 RGB->RGB kernel."""
    b, c, h, w = x.shape
    frames = c // 3
    weights = torch.randn(b, 3, 3, 3, 3) * math.sqrt(2.0 / 54.0)
    weights = weights[:, None].expand(-1, frames, -1, -1, -1, -1).reshape(b * frames * 3, 3, 3, 3)
    out = torch.nn.functional.conv2d(x.float().view(1, b * c, h, w), weights, padding=1, groups=b * frames)
    return out.view(b, c, h, w).clamp(0, 255).round().to(torch.uint8)


def _blend(img: torch.Tensor, other: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    return (ratio * img + (1 - ratio) * other).clamp(0, 1)


def _shift_hue(img: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    r, g, b = img.unbind(-3)
    maxc, _ = img.max(-3)
    minc, _ = img.min(-3)
    delta = maxc - minc
    sat = torch.where(maxc > 0, delta / torch.where(maxc > 0, maxc, torch.ones_like(maxc)), torch.zeros_like(maxc))
    div = torch.where(delta > 0, delta, torch.ones_like(delta))
    sextant = torch.where(maxc == r, (g - b) / div, torch.where(maxc == g, 2 + (b - r) / div, 4 + (r - g) / div))
    sextant = torch.where(delta > 0, sextant, torch.zeros_like(sextant))
    hue = torch.remainder(sextant / 6 + shift[..., 0, :, :], 1.0)
    scaled = hue * 6
    sector = scaled.floor().clamp(max=5)
    frac = scaled - sector
    p, q, t = maxc * (1 - sat), maxc * (1 - sat * frac), maxc * (1 - sat * (1 - frac))
    sector = sector.long()
    choices = torch.stack([maxc, q, p, p, t, maxc, t, maxc, maxc, q, p, p, p, p, t, maxc, maxc, q]).view(3, 6, *maxc.shape)
    index = sector[None, None].expand(3, 1, *sector.shape)
    return choices.gather(1, index).squeeze(1).movedim(0, -3)


def color_jitter(x: torch.Tensor, spread: float = 0.4, hue: float = 0.5) -> torch.Tensor:
    b, c, h, w = x.shape
    img = x.view(b, c // 3, 3, h, w).float() / 255
    shape = (b, 1, 1, 1, 1)
    factors = {
        "brightness": 1 - spread + 2 * spread * torch.rand(shape),
        "contrast": 1 - spread + 2 * spread * torch.rand(shape),
        "saturation": 1 - spread + 2 * spread * torch.rand(shape),
        "hue": -hue + 2 * hue * torch.rand(shape),
    }
    orders = torch.argsort(torch.rand(b, 4), dim=1)  # a random order per sample
    names = ["brightness", "contrast", "saturation", "hue"]
    for step in range(4):
        for op_index, name in enumerate(names):
            chosen = orders[:, step] == op_index
            if not chosen.any():
                continue
            part, factor = img[chosen], factors[name][chosen]
            if name == "brightness":
                part = _blend(part, torch.zeros_like(part), factor)
            elif name == "contrast":
                part = _blend(part, luma(part).mean(dim=(-3, -2, -1), keepdim=True), factor)
            elif name == "saturation":
                part = _blend(part, luma(part), factor)
            else:
                part = _shift_hue(part, factor)
            img[chosen] = part
    return (img * 255).round().clamp(0, 255).to(torch.uint8).view(b, c, h, w)


def shift(x: torch.Tensor, pad: int) -> torch.Tensor:
    """DrQ-v2's `RandomShiftsAug` (facebookresearch/drqv2 `drqv2.py`): replicate padding, then
    `grid_sample` at integer shifts; uint8 in and out like the other cases."""
    b, c, h, w = x.shape
    padded = torch.nn.functional.pad(x.float(), (pad, pad, pad, pad), mode="replicate")
    eps = 1.0 / (h + 2 * pad)
    arange = torch.linspace(-1.0 + eps, 1.0 - eps, h + 2 * pad)[:h]
    arange = arange.unsqueeze(0).repeat(h, 1).unsqueeze(2)
    base_grid = torch.cat([arange, arange.transpose(1, 0)], dim=2).unsqueeze(0).repeat(b, 1, 1, 1)
    shifts = torch.randint(0, 2 * pad + 1, size=(b, 1, 1, 2)).float() * 2.0 / (h + 2 * pad)
    out = torch.nn.functional.grid_sample(padded, base_grid + shifts, padding_mode="zeros", align_corners=False)
    return out.round().clamp(0, 255).to(torch.uint8)


def intensity(x: torch.Tensor, scale: float) -> torch.Tensor:
    """DrQ's `Intensity` (denisyarats/drq on Atari, SPR): one factor per sample."""
    factor = 1.0 + scale * torch.randn(x.shape[0]).clamp(-2.0, 2.0)
    return (x.float() * per_sample(x, factor)).round().clamp(0, 255).to(torch.uint8)


def crop_grayscale(x: torch.Tensor) -> torch.Tensor:
    return grayscale(crop(x, 84), 0.3)


TORCH = {
    "crop(84)": lambda x: crop(x, 84),
    "translate(108)": lambda x: translate(x, 108),
    "window(84)": lambda x: window(x, 84),
    "center_crop(84)": lambda x: center_crop(x, 84),
    "flip(p=1)": lambda x: flip(x, 1.0),
    "rotate(p=1)": lambda x: rotate(x, 1.0),
    "cutout(min=10,max=30)": lambda x: cutout(x, 10, 30, colour=False),
    "cutout_color(min=10,max=30)": lambda x: cutout(x, 10, 30, colour=True),
    "grayscale(p=1)": lambda x: grayscale(x, 1.0),
    "conv": random_conv,
    "color_jitter(brightness=0.4,contrast=0.4,saturation=0.4,hue=0.5)": color_jitter,
    "crop(84)|grayscale(p=0.3)": crop_grayscale,
    "shift(4)": lambda x: shift(x, 4),
    "intensity(scale=0.05)": lambda x: intensity(x, 0.05),
}


def time_torch(fn, x: torch.Tensor, budget_s: float) -> float:
    fn(x)  # warm-up
    times = []
    started = time.perf_counter()
    while len(times) < 3 or (time.perf_counter() - started < budget_s and len(times) < 15):
        t0 = time.perf_counter()
        fn(x)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--binary", default=str(ROOT / "target/release/radserve"))
    parser.add_argument("--budget", type=float, default=3.0, help="seconds of PyTorch timing per case")
    parser.add_argument("--filter", default="")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    command = [args.binary, "augment-bench", "--json", "--batch", str(args.batch), "--threads", str(args.threads),
               "--filter", args.filter]
    rows = [json.loads(line) for line in subprocess.run(command, check=True, capture_output=True, text=True).stdout.splitlines()]

    generator = torch.Generator().manual_seed(0)
    print(f"batch {args.batch}, {args.threads} thread(s), torch {torch.__version__}; ms per batch, median")
    header = f"{'pipeline':<28} {'output':>16} {'radserve':>9} {'GB/s':>6} {'x copy':>7} {'torch':>9} {'speed-up':>9}"
    print(header)
    print("-" * len(header))
    table_rows = []
    for row in rows:
        fn = TORCH[row["pipeline"]]
        x = torch.randint(0, 256, (args.batch, *row["input"]), dtype=torch.uint8, generator=generator)
        out = fn(x)
        assert list(out.shape[1:]) == row["output"], (row["pipeline"], out.shape, row["output"])
        torch_s = time_torch(fn, x, args.budget)
        ours = row["seconds"]
        name = row["pipeline"].split("(brightness")[0].replace("(min=10,max=30)", "")
        output = "x".join(str(d) for d in [args.batch, *row["output"]])
        print(f"{name:<28} {output:>16} {ours * 1e3:>9.2f} {row['output_bytes'] / ours / 1e9:>6.2f} "
              f"{ours / row['copy_seconds']:>7.2f} {torch_s * 1e3:>9.1f} {torch_s / ours:>8.1f}x")
        sys.stdout.flush()
        table_rows.append([f"`{name}`", output, record.cell(ours * 1e3, digits=2),
                           record.cell(row["output_bytes"] / ours / 1e9, digits=2),
                           record.cell(ours / row["copy_seconds"], digits=2), record.cell(torch_s * 1e3, digits=1),
                           record.cell(torch_s / ours, digits=1, suffix="x")])
    if not args.filter:
        table = {"id": "augment_speed", "rows": table_rows,
                 "columns": ["pipeline", "output", "radserve ms", "GB/s", "x copy", "PyTorch ms", "speed-up"],
                 "note": f"Batch {args.batch}, {args.threads} threads on both sides, medians; torch {torch.__version__}."}
        record.write("augment_speed", [table], {"batch": args.batch, "threads": args.threads, "budget": args.budget})


if __name__ == "__main__":
    main()
