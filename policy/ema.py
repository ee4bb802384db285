"""The EMA of a model's weights that training keeps and export ships."""

from __future__ import annotations

import copy

import torch


class EMA:
    """Exponential moving average of the weights with Diffusion Policy's warm-up of the decay:
    decay(k) = min(max_decay, 1 - (1 + k) ** -power), so early averages are short and later ones long."""

    def __init__(self, model: torch.nn.Module, power: float = 0.75, max_decay: float = 0.9999):
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.power, self.max_decay, self.updates = power, max_decay, 0

    def decay(self) -> float:
        return 0.0 if self.updates == 0 else min(self.max_decay, 1 - (1 + self.updates) ** -self.power)

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        d = self.decay()
        ours = list(self.model.parameters())
        # one fused kernel per op for all tensors: a per-tensor loop is ~2 launches per parameter on a GPU
        torch._foreach_mul_(ours, d)
        torch._foreach_add_(ours, [p.detach() for p in model.parameters()], alpha=1 - d)
        for e, b in zip(self.model.buffers(), model.buffers()):
            e.copy_(b)
        self.updates += 1

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.updates = state["updates"]
