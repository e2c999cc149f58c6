"""radserve's shift(4) against DrQ-v2's `RandomShiftsAug` (facebookresearch/drqv2 `drqv2.py`) run in
torch on the same shifts: replicate padding, then `grid_sample` at whole-pixel offsets on float
frames. The two agree up to float rounding of DrQ-v2's sampling grid (below 0.01 of a level), so
rounding DrQ-v2's output gives radserve's bytes exactly (docs/augmentations.md, "Where we differ").

Needs the learners' extra (torch): `make test` runs it after installing it, with
RADSERVE_REQUIRE_TORCH=1 so that a missing torch fails instead of skipping.
"""

import os

import numpy as np
import pytest

if os.environ.get("RADSERVE_REQUIRE_TORCH") != "1":
    pytest.importorskip("torch", reason="the comparison runs DrQ-v2's shift in torch (make torch)")

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

PAD = 4


class RandomShiftsAug(torch.nn.Module):
    """DrQ-v2's random shift, written from its definition: pad by `pad` repeating the edge, build a
    grid of the pixel centres of the unpadded frame in normalized coordinates of the padded one,
    move it by whole pixels drawn with `torch.randint(0, 2 * pad + 1)` (x then y), and sample with
    `grid_sample` (bilinear, zeros outside, align_corners=False)."""

    def __init__(self, pad):
        super().__init__()
        self.pad = pad

    def forward(self, x):
        n, _, h, w = x.shape
        assert h == w
        x = F.pad(x, (self.pad,) * 4, mode="replicate")
        side = h + 2 * self.pad
        eps = 1.0 / side
        centres = torch.linspace(-1.0 + eps, 1.0 - eps, side, dtype=x.dtype)[:h]
        xs = centres.unsqueeze(0).repeat(h, 1).unsqueeze(2)
        grid = torch.cat([xs, xs.transpose(1, 0)], dim=2).unsqueeze(0).repeat(n, 1, 1, 1)
        shift = torch.randint(0, 2 * self.pad + 1, size=(n, 1, 1, 2), dtype=x.dtype)
        shift *= 2.0 / side
        return F.grid_sample(x, grid + shift, padding_mode="zeros", align_corners=False)


def offsets_of(clean, shifted):
    """(top, left) in [0, 2 * PAD] at which `shifted` is the edge-padded `clean`, or None."""
    padded = np.pad(clean, ((0, 0), (PAD, PAD), (PAD, PAD)), mode="edge")
    side = clean.shape[1]
    for top in range(2 * PAD + 1):
        for left in range(2 * PAD + 1):
            if np.array_equal(padded[:, top:top + side, left:left + side], shifted):
                return top, left
    return None


def test_shift_equals_drqv2s_random_shifts_on_the_same_shifts(client, monkeypatch):
    envs = client.make_vec("dmc/walker-walk", num_envs=2, seed=3, replay_capacity=300, render_profile="fast",
                           height=84, width=84)
    try:
        envs.reset(seed=3)
        for _ in range(30):
            envs.step(envs.action_space.sample())
        with envs.sample_batches(128, views={"clean": "none", "shifted": "shift(4)"}, seed=7, max_batches=2,
                                 min_size=40) as stream:
            batches = [(batch.views["clean"].copy(), batch.views["shifted"].copy()) for batch in stream]
    finally:
        envs.close()
    clean = np.concatenate([c for c, _ in batches])
    shifted = np.concatenate([s for _, s in batches])
    offsets = [offsets_of(c, s) for c, s in zip(clean, shifted)]
    assert all(o is not None for o in offsets), "every shifted view is an edge-padded shift of the frame"
    assert len(set(offsets)) > 40, "offsets vary over the 81 possible"
    # DrQ-v2's module on the same frames, its randint answering with radserve's shifts (x, then y).
    drawn = torch.tensor([[left, top] for top, left in offsets], dtype=torch.float32).view(-1, 1, 1, 2)
    monkeypatch.setattr(torch, "randint", lambda low, high, size, dtype=None, **_: drawn.clone().to(dtype))
    with torch.no_grad():
        theirs = RandomShiftsAug(PAD)(torch.from_numpy(clean).float()).numpy()
    error = np.abs(theirs - shifted.astype(np.float32))
    assert error.max() < 0.01, f"DrQ-v2's shift differs by {error.max()} levels"
    np.testing.assert_array_equal(np.rint(theirs).astype(np.uint8), shifted)
