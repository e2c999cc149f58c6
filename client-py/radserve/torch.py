"""Minibatches as torch tensors: `for batch in radserve.torch.tensors(client.sample_batches(...), device="cuda")`.

Needs the `torch` extra (`pip install radserve[torch]`); nothing else in radserve imports torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Iterable, Iterator

import numpy as np
import torch

from .batches import Batch


@dataclass
class TensorBatch:
    """A Batch with every array as a tensor on `device` (uint8 observations stay uint8: scale them on
    the device, where it is cheap); `views` as a dict of tensors, `obs` and `next_obs` among them."""

    index: int
    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    env_index: torch.Tensor
    step_index: torch.Tensor
    next_obs: "torch.Tensor | None" = None
    t: "torch.Tensor | None" = None
    policy_version: "torch.Tensor | None" = None
    log_prob: "torch.Tensor | None" = None
    value: "torch.Tensor | None" = None
    server: "torch.Tensor | None" = None
    discount: "torch.Tensor | None" = None
    views: "dict[str, torch.Tensor]" = field(default_factory=dict)
    key: "torch.Tensor | None" = None
    probability: "torch.Tensor | None" = None
    table_size: "torch.Tensor | None" = None
    weight: "torch.Tensor | None" = None
    is_first: "torch.Tensor | None" = None
    is_last: "torch.Tensor | None" = None
    is_terminal: "torch.Tensor | None" = None
    mask: "torch.Tensor | None" = None

    def __len__(self) -> int:
        return len(self.reward)


def to_tensors(batch: Batch, device: "torch.device | str" = "cpu", *, pin_memory: bool = False) -> TensorBatch:
    """One Batch as tensors. The numpy arrays are shared, not copied, on the CPU; with `pin_memory`
    they are copied into page-locked memory first so that the copy to a GPU runs asynchronously."""
    device = torch.device(device)

    def move(value: np.ndarray) -> torch.Tensor:
        tensor = torch.from_numpy(value)
        if pin_memory and device.type == "cuda":
            tensor = tensor.pin_memory()
        return tensor.to(device, non_blocking=pin_memory)

    converted = {}
    views = {name: move(value) for name, value in batch.views.items()}
    for spec in fields(Batch):
        value = getattr(batch, spec.name)
        if spec.name == "views":
            converted["views"] = views
        elif spec.name in ("obs", "next_obs") and spec.name in views:
            converted[spec.name] = views[spec.name]  # one copy on the device for both names
        elif isinstance(value, np.ndarray):
            converted[spec.name] = move(value)
        else:
            converted[spec.name] = value
    return TensorBatch(**converted)


def tensors(batches: Iterable[Batch], device: "torch.device | str" = "cpu", *, pin_memory: bool = False) -> Iterator[TensorBatch]:
    """Every Batch of `batches` (e.g. `client.sample_batches(...)`) as a TensorBatch on `device`."""
    for batch in batches:
        yield to_tensors(batch, device, pin_memory=pin_memory)
