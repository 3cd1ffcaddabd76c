"""The off-policy family's networks: TorchRL modules for one run, and S seeds' copies as flat rows.

OmniSafe's SAC-Lag, TD3-Lag and DDPG-Lag networks (``configs/off-policy/*.yaml``): ReLU MLPs of
``[256, 256]``; SAC's actor a tanh-squashed Gaussian with a state-dependent scale, TD3's and DDPG's a
deterministic tanh actor; Q-critics reading the observation and the action.
:func:`make_off_policy_networks` builds them as the TorchRL modules ``SACLagLoss`` / ``TD3LagLoss`` /
``DDPGLagLoss`` take (what ``examples/sac_lag.py`` composes and what a checkpoint's entries load into).

:class:`StackedOffPolicyNets` holds S seeds' copies, each network kind as one ``(S, P)`` row-per-seed
tensor (twin critics: ``(S, K * P)``, critic ``k`` of seed ``s`` at row ``s * K + k`` once viewed as
``(S * K, P)``), run with one ``baddbmm`` per layer for all seeds and critics. The forward passes take
the parameters as an argument, which the off-policy steps need and the parameter-owning stacked layers of
:mod:`sg_torchrl.modules.stacked_layers` (tanh, for the on-policy family) do not give: the actor step
evaluates the critics with detached parameters, and the targets are further rows of the same layout
(Polyak averaging is one ``lerp_`` per network kind).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from tensordict.nn.utils import mappings
from torch import Tensor, nn
from torch.nn import functional as F
from torchrl.data import Bounded
from torchrl.modules import MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator
from torchrl.modules.distributions.utils import safetanh_noeps

from sg_torchrl.modules.gaussian import gaussian_log_prob
from sg_torchrl.modules.stacked_layers import stacked_mlp_forward

__all__ = ["FlatMLP", "SCALE_MAPPING", "StackedOffPolicyNets", "make_off_policy_networks"]

#: SAC's scale from the actor's second half of outputs (``NormalParamExtractor``'s default mapping).
SCALE_MAPPING = "biased_softplus_1.0"
_SCALE_LB = 1e-4


def _mlp(in_features: int, out_features: int, hidden: Sequence[int]) -> MLP:
    return MLP(in_features=in_features, out_features=out_features, num_cells=list(hidden), activation_class=nn.ReLU)


def make_off_policy_networks(obs_dim: int, action_spec: Bounded, hidden_sizes: Sequence[int], *, stochastic: bool,
                             num_critics: int, constrained: bool) -> tuple[nn.Module, list[nn.Module], list[nn.Module]]:
    """``(actor, reward critics, cost critics)`` of one run, freshly initialised from the global RNG.

    ``stochastic``: SAC's ``ProbabilisticActor`` (``TanhNormal`` over the action bounds), else a deterministic
    MLP with a ``TanhModule``. ``num_critics`` reward critics (``ValueOperator`` s writing
    ``"state_action_value"``), and as many cost critics when ``constrained`` (else an empty list).
    """
    action_dim = action_spec.shape[-1]
    if stochastic:
        body = TensorDictModule(nn.Sequential(_mlp(obs_dim, 2 * action_dim, hidden_sizes),
                                              NormalParamExtractor(scale_mapping=SCALE_MAPPING, scale_lb=_SCALE_LB)),
                                in_keys=["observation"], out_keys=["loc", "scale"])
        actor = ProbabilisticActor(body, in_keys=["loc", "scale"], spec=action_spec, distribution_class=TanhNormal,
                                   distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high})
    else:
        actor = TensorDictSequential(
            TensorDictModule(_mlp(obs_dim, action_dim, hidden_sizes), in_keys=["observation"], out_keys=["param"]),
            TanhModule(in_keys=["param"], out_keys=["action"], spec=action_spec))

    def critic() -> nn.Module:
        return ValueOperator(_mlp(obs_dim + action_dim, 1, hidden_sizes), in_keys=["observation", "action"])

    critics = [critic() for _ in range(num_critics)]
    costs = [critic() for _ in range(num_critics)] if constrained else []
    return actor, critics, costs


def _only_mlp(module: nn.Module) -> MLP:
    found = [m for m in module.modules() if isinstance(m, MLP)]
    if len(found) != 1:
        raise TypeError(f"expected exactly one MLP in {type(module).__name__}, found {len(found)}")
    return found[0]


class FlatMLP:
    """Where a ReLU MLP's weights sit in a flat row, and its forward pass for many rows at once.

    Layer ``i``'s weight is stored transposed, ``(in_i, out_i)``, then its bias ``(out_i,)``; ReLU between
    layers, none after the last (TorchRL's ``MLP(activation_class=nn.ReLU)``).
    """

    def __init__(self, sizes: Sequence[int]) -> None:
        self.sizes = tuple(int(s) for s in sizes)
        self.layers = []
        offset = 0
        for a, b in zip(self.sizes[:-1], self.sizes[1:]):
            self.layers.append((offset, a, b))
            offset += a * b + b
        self.numel = offset

    def forward(self, flat: Tensor, x: Tensor) -> Tensor:
        """``flat`` ``(R, numel)`` rows, ``x`` ``(R, B, in)`` to ``(R, B, out)``: row ``r`` sees its own weights."""
        rows = flat.shape[0]
        layers = ((flat[:, offset : offset + a * b].view(rows, a, b), flat[:, offset + a * b : offset + a * b + b]
                   .view(rows, 1, b)) for offset, a, b in self.layers)
        return stacked_mlp_forward(x, layers, F.relu)

    def module_outputs(self, flat: Tensor, x: Tensor) -> list[Tensor]:
        """Each row's :meth:`forward` as its own module computes it, one ``(B, out)`` tensor per row: one
        ``F.linear`` per row and layer on the weight in ``nn.Linear``'s ``(out, in)`` layout, so row ``r``'s
        output is its TorchRL module's bit for bit (a batched matmul, another weight layout, an unaligned input,
        or one elementwise kernel over all rows rounds differently)."""
        out = []
        for row, h in zip(flat, x):
            h = h.clone()  # freshly allocated: the BLAS kernels may round differently on a row not aligned as one
            for i, (offset, a, b) in enumerate(self.layers):
                weight = row[offset : offset + a * b].view(a, b).T.contiguous()
                h = F.linear(h, weight, row[offset + a * b : offset + a * b + b])
                if i < len(self.layers) - 1:
                    h = F.relu(h)
            out.append(h)
        return out

    def _linears(self, module: nn.Module) -> list[nn.Linear]:
        linears = [m for m in _only_mlp(module).modules() if isinstance(m, nn.Linear)]
        if tuple([linears[0].in_features] + [lin.out_features for lin in linears]) != self.sizes:
            raise ValueError(f"the module's layers {[(lin.in_features, lin.out_features) for lin in linears]} do not "
                             f"match the sizes {self.sizes}")
        return linears

    @torch.no_grad()
    def load(self, row: Tensor, module: nn.Module) -> None:
        """Copy the MLP inside ``module`` into ``row`` ``(numel,)``."""
        for (offset, a, b), linear in zip(self.layers, self._linears(module)):
            row[offset : offset + a * b].copy_(linear.weight.T.reshape(-1))
            row[offset + a * b : offset + a * b + b].copy_(linear.bias)

    @torch.no_grad()
    def store(self, row: Tensor, module: nn.Module) -> None:
        """Write ``row`` into the MLP inside ``module``."""
        for (offset, a, b), linear in zip(self.layers, self._linears(module)):
            linear.weight.copy_(row[offset : offset + a * b].view(a, b).T)
            linear.bias.copy_(row[offset + a * b : offset + a * b + b])


class StackedOffPolicyNets:
    """S seeds' actor, reward critics and cost critics (and their targets) as ``(S, P)`` tensors.

    Args:
        num_seeds: S.
        obs_dim, action_spec: what the env emits and takes (bounded actions).
        hidden_sizes: hidden widths of every network.
        stochastic: SAC's squashed Gaussian actor (else a deterministic tanh actor with a target copy).
        num_critics: K reward critics (and K cost critics when ``constrained``).
        constrained: whether there are cost critics.
        device: where the rows, the targets and the action bounds live (``sg-train --device``); the modules
            :meth:`export_seed` builds and :meth:`load_seed` reads may live anywhere (a trainer's are on the CPU).

    Attributes:
        actor, critic, cost_critic: the trained rows (leaves with gradients); ``cost_critic`` ``None``
            when unconstrained.
        target_actor, target_critic, target_cost_critic: the target rows (``target_actor`` ``None`` for SAC,
            whose targets use the current actor).
    """

    def __init__(self, num_seeds: int, obs_dim: int, action_spec: Bounded, hidden_sizes: Sequence[int], *,
                 stochastic: bool, num_critics: int, constrained: bool,
                 device: torch.device | str | None = None) -> None:
        self.num_seeds, self.obs_dim, self.action_spec = int(num_seeds), int(obs_dim), action_spec
        self.hidden_sizes, self.stochastic = list(hidden_sizes), stochastic
        self.num_critics, self.constrained = int(num_critics), constrained
        action_dim = self.action_dim
        self.actor_layout = FlatMLP([obs_dim, *hidden_sizes, (2 if stochastic else 1) * action_dim])
        self.critic_layout = FlatMLP([obs_dim + action_dim, *hidden_sizes, 1])
        low, high = action_spec.space.low.float().to(device), action_spec.space.high.float().to(device)
        self.low, self.high = low, high
        # TanhNormal's affine map after its tanh, present when the bounds are not [-1, 1] (TanhModule always rescales)
        self.affine = (high + low) / 2, (high - low) / 2
        self.unit_bounds = not bool((low != -1).any() or (high != 1).any())
        self._scale_mapping = mappings(SCALE_MAPPING)

        def rows(width: int, grad: bool) -> Tensor:
            return torch.zeros(num_seeds, width, requires_grad=grad, device=device)

        critics = num_critics * self.critic_layout.numel
        self.actor = rows(self.actor_layout.numel, True)
        self.critic = rows(critics, True)
        self.cost_critic = rows(critics, True) if constrained else None
        self.target_actor = None if stochastic else rows(self.actor_layout.numel, False)
        self.target_critic = rows(critics, False)
        self.target_cost_critic = rows(critics, False) if constrained else None

    @property
    def device(self) -> torch.device:
        """Where the rows live."""
        return self.actor.device

    @property
    def action_dim(self) -> int:
        return int(self.action_spec.shape[-1])

    def trained(self) -> dict[str, Tensor]:
        """The trained rows by name (what the optimisers step)."""
        out = {"actor": self.actor, "critic": self.critic}
        if self.constrained:
            out["cost_critic"] = self.cost_critic
        return out

    def targets(self) -> dict[str, Tensor]:
        """Each target's rows by the name of the trained rows it follows."""
        out = {"critic": self.target_critic}
        if self.constrained:
            out["cost_critic"] = self.target_cost_critic
        if self.target_actor is not None:
            out["actor"] = self.target_actor
        return out

    # ------------------------------------------------------------------ forward passes
    # The actions below are the TorchRL actor's operations in its order (``TanhModule.forward``; ``TanhNormal``'s
    # transforms, ``deterministic_sample`` and ``rsample_and_log_prob``), seed by seed on that seed's own tensors
    # (``FlatMLP.module_outputs``), so collection, the actor's steps and the exported actor compute the same bits.
    def _squashed(self, x: Tensor) -> Tensor:
        """``TanhNormal``'s transform: TorchRL's safe tanh, then ``loc + scale * y`` unless the bounds are [-1, 1]."""
        y = safetanh_noeps(x)
        return y if self.unit_bounds else self.affine[0] + self.affine[1] * y

    def action(self, actor: Tensor, obs: Tensor) -> Tensor:
        """The deterministic action, ``(S, B, A)``: SAC's squashed mean (``TanhNormal.deterministic_sample``), TD3's
        and DDPG's ``TanhModule`` output (``low + (high - low) * (tanh(x) + 1) / 2``, [-1, 1] bounds included)."""
        outputs = self.actor_layout.module_outputs(actor, obs)
        if self.stochastic:
            return torch.stack([self._squashed(out[..., : self.action_dim]) for out in outputs])
        return torch.stack([self.low + (self.high - self.low) * (out.tanh() + 1) / 2 for out in outputs])

    def sample(self, actor: Tensor, obs: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
        """SAC's reparameterised action and its log-probability from standard-normal ``noise`` ``(S, B, A)``:
        ``TanhNormal.rsample_and_log_prob`` with ``noise`` as the Gaussian's draw.

        The log-probability is the Gaussian's (``Normal.log_prob``) of the pre-tanh value minus the transforms'
        :math:`\log |d\,\text{action} / d x|` (tanh's :math:`2 (\log 2 - x - \text{softplus}(-2x))`, plus
        :math:`\log` of the affine scale when the bounds are not [-1, 1]), each summed over the action.
        """
        actions, log_probs = [], []
        for out, draw in zip(self.actor_layout.module_outputs(actor, obs), noise):
            loc, raw = out.chunk(2, -1)
            scale = self._scale_mapping(raw).clamp_min(_SCALE_LB)
            pre = loc + draw * scale  # in TorchRL's order throughout: the gradients sum in the same order too
            actions.append(self._squashed(pre))
            gaussian = gaussian_log_prob(pre, loc, scale)
            jacobian = 2.0 * (math.log(2.0) - pre - F.softplus(-2.0 * pre))
            if not self.unit_bounds:
                jacobian = jacobian + self.affine[1].abs().log()
            log_probs.append(gaussian - jacobian.sum(-1))
        return torch.stack(actions), torch.stack(log_probs)

    def q(self, rows: Tensor, obs: Tensor, action: Tensor) -> Tensor:
        """The K critics in ``rows`` (``(S, K * P)``) at ``(obs, action)`` ``(S, B, ...)``: ``(S, K, B)``."""
        seeds, batch = obs.shape[:2]
        k = self.num_critics
        x = torch.cat([obs, action], -1)
        x = x.unsqueeze(1).expand(seeds, k, batch, x.shape[-1]).reshape(seeds * k, batch, x.shape[-1])
        return self.critic_layout.forward(rows.view(seeds * k, -1), x).view(seeds, k, batch)

    @torch.no_grad()
    def soft_update(self, tau: float, names: Sequence[str]) -> None:
        """Polyak-average the targets of ``names`` towards their trained rows: ``target += tau * (trained - target)``."""
        trained, targets = self.trained(), self.targets()
        for name in names:
            targets[name].lerp_(trained[name], tau)

    # ------------------------------------------------------------------ single-seed modules
    def _critic_rows(self, rows: Tensor, seed: int) -> Tensor:
        return rows[seed].view(self.num_critics, -1)

    @torch.no_grad()
    def load_seed(self, seed: int, actor: nn.Module, critics: Sequence[nn.Module], costs: Sequence[nn.Module]) -> None:
        """Copy one run's modules (:func:`make_off_policy_networks`'s) into seed ``seed``; the targets start equal."""
        self.actor_layout.load(self.actor[seed], actor)
        for rows, modules in ((self.critic, critics), (self.cost_critic, costs)):
            if rows is None:
                continue
            if len(modules) != self.num_critics:
                raise ValueError(f"expected {self.num_critics} critics, got {len(modules)}")
            for k, module in enumerate(modules):
                self.critic_layout.load(self._critic_rows(rows, seed)[k], module)
        for name, target in self.targets().items():
            target[seed].copy_(self.trained()[name][seed])

    def export_seed(self, seed: int) -> tuple[nn.Module, list[nn.Module], list[nn.Module]]:
        """Seed ``seed``'s trained networks as fresh :func:`make_off_policy_networks` modules (the global RNG is untouched)."""
        with torch.random.fork_rng(devices=[]):
            actor, critics, costs = make_off_policy_networks(
                self.obs_dim, self.action_spec, self.hidden_sizes, stochastic=self.stochastic,
                num_critics=self.num_critics, constrained=self.constrained)
        self.actor_layout.store(self.actor[seed].detach(), actor)
        for rows, modules in ((self.critic, critics), (self.cost_critic, costs)):
            for k, module in enumerate(modules):
                self.critic_layout.store(self._critic_rows(rows.detach(), seed)[k], module)
        return actor, critics, costs

    @classmethod
    def from_single(cls, networks: Sequence[tuple[nn.Module, list, list]], obs_dim: int, action_spec: Bounded,
                    hidden_sizes: Sequence[int], *, stochastic: bool,
                    device: torch.device | str | None = None) -> StackedOffPolicyNets:
        """Stack S runs' :func:`make_off_policy_networks` outputs (seed ``s`` from ``networks[s]``) on ``device``."""
        first = networks[0]
        stacked = cls(len(networks), obs_dim, action_spec, hidden_sizes, stochastic=stochastic,
                      num_critics=len(first[1]), constrained=bool(first[2]), device=device)
        for seed, triple in enumerate(networks):
            stacked.load_seed(seed, *triple)
        return stacked
