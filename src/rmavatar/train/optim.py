"""Adam with the paper's learning rates: ``OptimConfig.build(avatar)``, and the position lr schedule."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from rmavatar.utils import UserError
from rmavatar.utils.config import check_fields


def position_lr(iteration: int, total: int, lr_start: float, lr_end: float) -> float:
    """3DGS's log-linear decay: lr_start at iteration 0, lr_end at iteration ``total``."""
    t = min(max(iteration / max(total, 1), 0.0), 1.0)
    return math.exp(math.log(lr_start) * (1.0 - t) + math.log(lr_end) * t)


@dataclass
class OptimConfig:
    """Adam with the paper's learning rates (positions in triangle-local units) and the run length."""

    iters: int = 50_000  # training iterations (the paper's 50,000)
    # --- advanced ---
    lr_position: float = 0.008  # Gaussian positions, at the first iteration
    lr_position_final: float = 1e-5  # reached log-linearly at the last iteration
    lr_scaling: float = 0.017  # log-scales
    lr_rotation: float = 0.001  # quaternions
    lr_opacity: float = 0.05  # opacity logits
    lr_color: float = 0.0025  # SH band 0; higher bands use lr_color / sh_rest_divisor
    sh_rest_divisor: float = 20.0  # how much slower the higher SH bands learn (3DGS)
    lr_rectifier: float = 1e-4  # the rectifier MLP's weights
    adam_eps: float = 1e-15  # Adam's epsilon (3DGS)

    def validate(self) -> "OptimConfig":
        check_fields(self, "optim", positive=("adam_eps", "sh_rest_divisor"),
                     nonnegative=("lr_scaling", "lr_rotation", "lr_opacity", "lr_color", "lr_rectifier"))
        if self.iters < 1:
            raise UserError(f"optim.iters (--iters) must be >= 1, got {self.iters}")
        if self.lr_position_final <= 0 or self.lr_position <= 0:
            raise UserError("optim.lr_position and optim.lr_position_final must be > 0")
        return self

    def build(self, avatar) -> torch.optim.Adam:
        """Adam over named parameter groups (eps ``adam_eps``).

        Group order and names are fixed, so a checkpoint's optimiser state loads into a rebuilt one; the
        "position" group's lr follows :meth:`position_lr`, set every step by the trainer.
        """
        groups = [
            {"name": "position", "params": [avatar.means], "lr": self.lr_position},
            {"name": "rotation", "params": [avatar.quats], "lr": self.lr_rotation},
            {"name": "scaling", "params": [avatar.log_scales], "lr": self.lr_scaling},
            {"name": "opacity", "params": [avatar.opacity_logits], "lr": self.lr_opacity},
            {"name": "sh_dc", "params": [avatar.sh_dc], "lr": self.lr_color},
            {"name": "sh_rest", "params": [avatar.sh_rest], "lr": self.lr_color / self.sh_rest_divisor},
        ]
        if avatar.rectifier is not None:
            groups.append({"name": "rectifier", "params": list(avatar.rectifier.parameters()), "lr": self.lr_rectifier})
        # Fused Adam (CPU and CUDA) skips a step on the device (``found_inf``), which the trainer's NaN
        # guard relies on; OneLaunchAdam runs it over all groups at once. Elsewhere: plain Adam.
        if avatar.means.device.type in ("cpu", "cuda"):
            return OneLaunchAdam(groups, lr=self.lr_position, eps=self.adam_eps)
        return torch.optim.Adam(groups, lr=self.lr_position, eps=self.adam_eps)

    def position_lr(self, iteration: int) -> float:
        """The position group's lr before step ``iteration + 1`` (0-based count of steps done)."""
        return position_lr(iteration, self.iters, self.lr_position, self.lr_position_final)


class OneLaunchAdam(torch.optim.Adam):
    """``torch.optim.Adam(fused=True)`` whose step is six tensor operations for all its groups together,
    not three per group; same results up to float rounding, same state (``step``, ``exp_avg``,
    ``exp_avg_sq`` per parameter), so its state_dict is a torch Adam's and loads into one.

    One fused Adam kernel needs one lr, so it runs with lr 1 on update buffers U (zeroed first, standing
    in for the parameters); then U *= each parameter's group lr and params += U. ``found_inf`` (a 0-d
    float tensor, 1.0 = skip, as set by ``torch.amp.GradScaler`` or the trainer) makes the kernel write
    nothing, so U stays zero and the step counts are put back: the step changes nothing, without a host
    sync. Groups that differ in betas, eps, amsgrad or maximize get one kernel each. Weight decay is
    not supported (the kernel would decay U, not the parameter); lr must be a number.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 amsgrad: bool = False, maximize: bool = False):
        super().__init__(params, lr=lr, betas=betas, eps=eps, amsgrad=amsgrad, maximize=maximize, fused=True)
        self._updates: dict = {}  # parameter -> its U buffer (not state: recreated after density surgery)

    def add_param_group(self, param_group: dict) -> None:
        if param_group.get("weight_decay") or param_group.get("decoupled_weight_decay"):
            raise ValueError("OneLaunchAdam does not support weight decay")
        super().add_param_group(param_group)

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        buckets: dict = {}
        for group in self.param_groups:
            if torch.is_tensor(group["lr"]):
                raise ValueError("OneLaunchAdam needs a number as lr, not a tensor")
            params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps = [], [], [], [], [], []
            self._init_group(group, params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps)
            for i, p in enumerate(params):
                key = (p.device, p.dtype, *group["betas"], group["eps"], group["amsgrad"], group["maximize"])
                lists = buckets.setdefault(key, ([], [], [], [], [], [], []))
                lists[6].append(group["lr"])
                for dst, src in zip(lists, (params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps)):
                    if src:
                        dst.append(src[i])
        updates: dict = {}
        grad_scale = getattr(self, "grad_scale", None)
        found_inf = getattr(self, "found_inf", None)
        for (device, dtype, beta1, beta2, eps, amsgrad, maximize), lists in buckets.items():
            params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps, lrs = lists
            u = []
            for p in params:
                buf = self._updates.get(p)
                u.append(buf if buf is not None and buf.shape == p.shape else torch.empty_like(p))
                updates[p] = u[-1]
            skip = None if found_inf is None else found_inf.to(device)
            torch._foreach_zero_(u)
            torch._foreach_add_(steps, 1)
            torch._fused_adam_(u, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps, lr=1.0, beta1=beta1,
                               beta2=beta2, weight_decay=0.0, eps=eps, amsgrad=amsgrad, maximize=maximize,
                               grad_scale=None if grad_scale is None else grad_scale.to(device), found_inf=skip)
            if skip is not None:  # a list of the one tensor: a tensor scalar would be read on the host
                torch._foreach_sub_(steps, [skip] * len(steps))
            torch._foreach_mul_(u, lrs)
            torch._foreach_add_(params, u)
        self._updates = updates
        return loss
