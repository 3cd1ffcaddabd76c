"""Adam for a seed group: per-seed step counts, per-seed gradient clip, and a mask that freezes seeds.

A seed group (DESIGN.md, "Many seeds in one process") keeps S runs' parameters stacked along a
leading seed dimension and steps them with one optimiser. Each run must still move exactly as its
single-seed trainer moves it: SafePO's first-order loop clips the global gradient norm of *its*
actor and critics at ``max_grad_norm`` (``clip_grad_norm_``) and then takes Adam steps, and it
stops moving once its KL early stop fires. :class:`SeedMaskedAdam` does this per seed: step counts
and bias corrections ``(S,)``, the clip norm taken per seed (:func:`clip_grad_norm_per_seed_`), and
an ``active`` mask ``(S,)`` under which an inactive seed's parameters, moments and step count do
not change at all while the others step. Its arithmetic is ``torch.optim.Adam``'s: each seed's rows
equal the default CPU (single-tensor) implementation's bit for bit, the fused kernel's to float
rounding (``tests/test_stacked.py``). It updates each group with ``torch._foreach_*`` ops (about
fifteen per group, whatever the group's size; on the flat buffers of
:class:`~sg_torchrl.modules.stacked.StackedActorCritic` a group is one tensor).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from sg_torchrl.train.checkpoint import host_copy
from sg_torchrl.train.compiling import CompileFallback

__all__ = ["SeedMaskedAdam", "clip_grad_norm_per_seed_"]


def clip_grad_norm_per_seed_(grads: Sequence[Tensor], max_norm: float, *, eps: float = 1e-6) -> Tensor:
    """Clip each seed's gradient to norm ``max_norm``; returns each seed's norm before clipping, ``(S,)``.

    Every tensor has a leading seed dimension; seed ``s``'s norm is taken over its slices of all
    ``grads`` (say the actor and both critics of that seed, nothing of another seed), with
    ``clip_grad_norm_``'s formula: the norm of the per-tensor norms, then the factor
    ``min(max_norm / (norm + 1e-6), 1)``.
    """
    norms = [torch.linalg.vector_norm(g, dim=tuple(range(1, g.dim()))) if g.dim() > 1 else g.abs() for g in grads]
    # (S, tensors): each seed's norms contiguous, reduced as one seed's alone are (S-independent rounding)
    total = norms[0] if len(norms) == 1 else torch.linalg.vector_norm(torch.stack(norms, dim=-1), dim=-1)
    coef = (max_norm / (total + eps)).clamp_(max=1.0)
    torch._foreach_mul_(list(grads), [coef.view(-1, *([1] * (g.dim() - 1))) for g in grads])
    return total


def _seed_view(values: Tensor, shapes: Sequence[tuple[int, ...]]) -> list[Tensor]:
    return [values.view(shape) for shape in shapes]


def _masked_adam_(
    groups: Sequence[tuple[list[Tensor], list[Tensor], list[Tensor], list[Tensor], Tensor, Tensor]],
    active: Tensor | None,
    beta1: float,
    beta2: float,
    eps: float,
    max_grad_norm: float | None,
    decompose_lerp: bool = False,
) -> Tensor | None:
    """Clip (optionally) and take one masked Adam step; the arithmetic of :class:`SeedMaskedAdam`.

    ``groups``: per parameter group ``(params, grads, exp_avgs, exp_avg_sqs, step, lr)``, with
    ``step`` the group's per-seed step counts (``(S,)`` float64) and ``lr`` a float64 tensor, ``()``
    or ``(S,)``. A pure function of tensors, so ``torch.compile`` can fuse it (``decompose_lerp``
    writes the masked first-moment ``lerp`` as sub, mul, add, which inductor fuses and does not
    otherwise; the same formula as ``lerp`` for weights below 0.5, up to a fused multiply-add).
    """
    norms = None
    if max_grad_norm is not None:
        norms = clip_grad_norm_per_seed_([g for group in groups for g in group[1]], max_grad_norm)
    mask = None if active is None else active.to(torch.float64)
    for params, grads, exp_avgs, exp_avg_sqs, step, lr in groups:
        dtype = params[0].dtype
        shapes = [(-1, *([1] * (p.dim() - 1))) for p in params]
        if mask is None:
            step += 1
            count = step
        else:
            step += mask
            count = step.clamp_min(1.0)  # a seed masked from its first step has no bias correction yet
        # torch.optim.Adam's scalars, per seed and in double precision like its Python floats.
        bias_correction1 = 1 - torch.pow(beta1, count)
        bias_correction2 = 1 - torch.pow(beta2, count)
        step_size = lr / bias_correction1
        if mask is not None:
            step_size = step_size * mask
        neg_step_size = _seed_view((-step_size).to(dtype), shapes)
        bias_correction2_sqrt = _seed_view(bias_correction2.sqrt().to(dtype), shapes)
        if mask is None:
            torch._foreach_lerp_(exp_avgs, grads, 1 - beta1)
            torch._foreach_mul_(exp_avg_sqs, beta2)
            torch._foreach_addcmul_(exp_avg_sqs, grads, grads, value=1 - beta2)
        else:
            keep = mask.to(dtype)
            # Inactive seeds: lerp weight 0, decay 1 and a zero square leave both moments as they are.
            masked_grads = torch._foreach_mul(grads, _seed_view(keep, shapes))
            weights = _seed_view(keep * (1 - beta1), shapes)
            if decompose_lerp:  # inductor has no lowering of lerp with per-tensor weights; this fuses
                step_to_grad = torch._foreach_sub(grads, exp_avgs)
                torch._foreach_mul_(step_to_grad, weights)
                torch._foreach_add_(exp_avgs, step_to_grad)
            else:
                torch._foreach_lerp_(exp_avgs, grads, weights)
            torch._foreach_mul_(exp_avg_sqs, _seed_view((1 - keep) + keep * beta2, shapes))
            torch._foreach_addcmul_(exp_avg_sqs, grads, masked_grads, value=1 - beta2)
        denom = torch._foreach_sqrt(exp_avg_sqs)
        torch._foreach_div_(denom, bias_correction2_sqrt)
        torch._foreach_add_(denom, eps)
        # param.addcdiv_(exp_avg, denom, value=-step_size) computes (value * exp_avg) / denom: same order.
        update = torch._foreach_mul(exp_avgs, neg_step_size)
        torch._foreach_div_(update, denom)
        torch._foreach_add_(params, update)
    return norms


class SeedMaskedAdam:
    """Adam over seed-stacked tensors, with per-seed step counts, gradient clip and an ``active`` mask.

    Each tensor of ``param_groups`` has a leading seed dimension S (e.g. the two flat buffers of a
    :class:`~sg_torchrl.modules.stacked.StackedActorCritic`, or stacked parameters), and gradients are
    read from their ``.grad``. Per group: ``lr`` (a float, or an ``(S,)`` tensor for per-seed rates;
    change ``param_groups[i]["lr"]`` to anneal) and per-seed step counts ``(S,)``. The arithmetic is
    ``torch.optim.Adam``'s (no weight decay, no AMSGrad): first moment by ``lerp``, second by
    ``mul`` + ``addcmul``, ``eps`` added after dividing the square root of the second moment by the
    square root of its bias correction, and the update as ``addcdiv`` orders it, so seed ``s`` of a
    group tracks a ``torch.optim.Adam`` over that seed's slices to float rounding. All tensors of a
    group are updated by ``torch._foreach_*`` ops: about fifteen ops per group, whatever its size.

    Args:
        param_groups: ``[{"params": [tensors], "lr": lr}, ...]``.
        betas, eps: Adam's.
        max_grad_norm: clip each seed's gradient (its norm over the groups being stepped) to this
            before the step, as ``clip_grad_norm_`` does per run (:func:`clip_grad_norm_per_seed_`);
            ``None``: no clip.
        compile: run the update through ``torch.compile`` (falls back to eager, with a warning,
            when compiling fails).
    """

    def __init__(
        self,
        param_groups: Sequence[Mapping],
        *,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        max_grad_norm: float | None = None,
        compile: bool = False,
    ) -> None:
        self.param_groups = [{"params": list(group["params"]), "lr": group["lr"]} for group in param_groups]
        if not self.param_groups or not all(group["params"] for group in self.param_groups):
            raise ValueError("SeedMaskedAdam needs parameter groups with at least one tensor each")
        seeds = {p.shape[0] for group in self.param_groups for p in group["params"]}
        if len(seeds) != 1:
            raise ValueError(f"all tensors need the same leading seed dimension, got sizes {sorted(seeds)}")
        self.num_seeds = seeds.pop()
        self.betas = (float(betas[0]), float(betas[1]))
        self.eps = float(eps)
        self.max_grad_norm = None if max_grad_norm is None else float(max_grad_norm)
        device = self.param_groups[0]["params"][0].device
        self.state = [
            {
                "step": torch.zeros(self.num_seeds, dtype=torch.float64, device=device),
                "exp_avg": [torch.zeros_like(p, memory_format=torch.preserve_format) for p in group["params"]],
                "exp_avg_sq": [torch.zeros_like(p, memory_format=torch.preserve_format) for p in group["params"]],
            }
            for group in self.param_groups
        ]
        self._lr = [torch.zeros((), dtype=torch.float64, device=device) for _ in self.param_groups]
        self._lr_seen: list[float | None] = [None] * len(self.param_groups)
        #: The update, compiled or eager (its ``compiled`` and ``compile_error`` say which, and why); the compiled
        #: form writes the masked first moment as sub, mul, add, which inductor fuses (see ``_masked_adam_``).
        self.compilation = CompileFallback(_masked_adam_, owner="SeedMaskedAdam", compile=compile,
                                           compiled_form=functools.partial(_masked_adam_, decompose_lerp=True))

    def _lr_tensor(self, index: int) -> Tensor:
        lr = self.param_groups[index]["lr"]
        if isinstance(lr, Tensor):
            return lr.to(torch.float64)
        if lr != self._lr_seen[index]:  # refreshed in place: a compiled update sees a tensor, never recompiles
            self._lr[index].fill_(float(lr))
            self._lr_seen[index] = lr
        return self._lr[index]

    @torch.no_grad()
    def step(self, active: Tensor | None = None, groups: Sequence[int] | None = None) -> Tensor | None:
        """One update of the groups ``groups`` (default: all) for the seeds where ``active`` is true.

        Args:
            active: ``(S,)`` bool or 0/1 float; ``None``: every seed. An inactive seed's
                parameters, moments and step count are left exactly as they are (its gradient
                must be finite: it is multiplied by 0).
            groups: indices of the groups to step (CUP's projection steps the actor alone); the
                others keep their parameters, moments and step counts.

        Returns:
            Each seed's gradient norm before clipping, ``(S,)``, with ``max_grad_norm``; else ``None``.
        """
        chosen = range(len(self.param_groups)) if groups is None else groups
        packed = []
        for index in chosen:
            params = self.param_groups[index]["params"]
            state = self.state[index]
            packed.append((params, [p.grad for p in params], state["exp_avg"], state["exp_avg_sq"], state["step"],
                           self._lr_tensor(index)))
        beta1, beta2 = self.betas
        return self.compilation(packed, active, beta1, beta2, self.eps, self.max_grad_norm)

    def state_dict(self) -> dict:
        """Moments and step counts of every group (the groups' tensors are the model's to save)."""
        return {
            "state": [{"step": s["step"].clone(), "exp_avg": [t.clone() for t in s["exp_avg"]],
                       "exp_avg_sq": [t.clone() for t in s["exp_avg_sq"]]} for s in self.state],
            "lr": [group["lr"] for group in self.param_groups],
            "betas": self.betas, "eps": self.eps, "max_grad_norm": self.max_grad_norm,
        }

    @torch.no_grad()
    def load_state_dict(self, state: Mapping) -> None:
        """Restore what :meth:`state_dict` saved (copied into the existing tensors)."""
        for mine, saved in zip(self.state, state["state"], strict=True):
            mine["step"].copy_(saved["step"])
            torch._foreach_copy_(mine["exp_avg"], list(saved["exp_avg"]))
            torch._foreach_copy_(mine["exp_avg_sq"], list(saved["exp_avg_sq"]))
        for group, lr in zip(self.param_groups, state["lr"], strict=True):
            group["lr"] = lr

    # ------------------------------------------------------------------ one seed's rows
    def seed_state_dict(self, index: int) -> list[dict]:
        """Seed ``index``'s rows of the state: per group its step count and the rows of both moments.

        CPU copies whatever the device (a checkpoint's: it loads, and continues, on any device)."""
        return host_copy([{"step": state["step"][index], "exp_avg": [t[index] for t in state["exp_avg"]],
                           "exp_avg_sq": [t[index] for t in state["exp_avg_sq"]]} for state in self.state])

    @torch.no_grad()
    def load_seed_state_dict(self, index: int, state: Sequence[Mapping]) -> None:
        """Restore what :meth:`seed_state_dict` saved into seed ``index``'s rows; the other seeds' are untouched."""
        for mine, saved in zip(self.state, state, strict=True):
            mine["step"][index] = saved["step"]
            for name in ("exp_avg", "exp_avg_sq"):
                for tensor, row in zip(mine[name], saved[name], strict=True):
                    tensor[index].copy_(row)

    @torch.no_grad()
    def restore_seeds(self, seeds: Tensor, state: Mapping) -> None:
        """Put the rows of the seeds where ``seeds`` (``(S,)`` bool) is true back to ``state`` (a :meth:`state_dict`).

        The other seeds' rows are untouched: a seed group puts back a failed update's seeds alone."""
        for mine, saved in zip(self.state, state["state"], strict=True):
            mine["step"].copy_(torch.where(seeds, saved["step"], mine["step"]))
            for name in ("exp_avg", "exp_avg_sq"):
                for current, old in zip(mine[name], saved[name], strict=True):
                    current.copy_(torch.where(seeds.view(-1, *([1] * (current.dim() - 1))), old, current))
