"""The algorithm manifest: every algorithm ``sg-train`` runs, one row each, and nowhere else.

Plain data, free of torch (importing it loads neither torch nor TorchRL), so that the command line,
the config check and the sweep can list, check and describe algorithms in a second. Everything that
needs an algorithm's name, title, kind or paper defaults reads these rows: the config
(:mod:`sg_torchrl.train.config`: ``--algo`` choices, :data:`~sg_torchrl.train.config.ALGORITHM_DEFAULTS`),
the single-agent builders (:mod:`sg_torchrl.train.algorithms`, which choose a row's multiplier, loss and
update builders by its :attr:`~AlgorithmEntry.multiplier`, :attr:`~AlgorithmEntry.loss` and
:attr:`~AlgorithmEntry.update`), the multi-agent rounds (:mod:`sg_torchrl.train.multi_agent`), the
sweep's report (paper names, baselines) and the benchmarks.

==========  =========  ======  ============  ===========  ==========  ===========================
name        title      agents  family        update       multiplier  loss
==========  =========  ======  ============  ===========  ==========  ===========================
pg          PG         single  first order   first_order  none        PGLoss
ppo         PPO        single  first order   first_order  none        PPOLagLoss
ppo_lag     PPO-Lag    single  first order   first_order  lagrange    PPOLagLoss
cppo_pid    CPPO-PID   single  first order   first_order  pid         PPOLagLoss
focops      FOCOPS     single  first order   first_order  lagrange    FOCOPSLoss
cup         CUP        single  first order   two_stage    lagrange    CUPLoss
npg         NPG        single  second order  natural      none        PPOLagLoss (critics)
trpo        TRPO       single  second order  trpo         none        PPOLagLoss (critics)
trpo_lag    TRPO-Lag   single  second order  trpo         lagrange    PPOLagLoss (critics)
rcpo        RCPO       single  second order  natural      lagrange    PPOLagLoss (critics)
cpo         CPO        single  second order  cpo          none        PPOLagLoss (critics)
pcpo        PCPO       single  second order  pcpo         none        PPOLagLoss (critics)
mappo       MAPPO      multi   first order   first_order  none        AgentPPOLoss (MAPPOUpdate)
happo       HAPPO      multi   first order   first_order  none        AgentPPOLoss (HAPPOUpdate)
mappo_lag   MAPPO-Lag  multi   first order   first_order  lagrange    AgentPPOLoss (MAPPOLagUpdate)
macpo       MACPO      multi   second order  cpo          none        AgentPPOLoss (MACPOUpdate)
sac         SAC        single  off policy    off_policy   none        SACLagLoss
td3         TD3        single  off policy    off_policy   none        TD3LagLoss
ddpg        DDPG       single  off policy    off_policy   none        DDPGLagLoss
sac_lag     SAC-Lag    single  off policy    off_policy   lagrange    SACLagLoss
td3_lag     TD3-Lag    single  off policy    off_policy   lagrange    TD3LagLoss
ddpg_lag    DDPG-Lag   single  off policy    off_policy   lagrange    DDPGLagLoss
sac_pid     SAC-PID    single  off policy    off_policy   pid         SACLagLoss
td3_pid     TD3-PID    single  off policy    off_policy   pid         TD3LagLoss
ddpg_pid    DDPG-PID   single  off policy    off_policy   pid         DDPGLagLoss
==========  =========  ======  ============  ===========  ==========  ===========================

Update kinds: ``off_policy`` (the off-policy family, beyond the paper: gradient steps on replayed
transitions interleaved with collection, :mod:`sg_torchrl.train.off_policy`), ``first_order`` (SafePO's minibatch passes with a KL early stop), ``two_stage`` (CUP: a
reward stage, then the projection), and the trust-region steps of the actor, ``natural`` (NPG's
step, no line search), ``trpo``, ``cpo`` and ``pcpo``. A multi-agent row's update is its
:attr:`~AlgorithmEntry.round` (the agents updated one at a time): first-order clipped-PPO epochs per
agent, or MACPO's per-agent CPO step. Multiplier kinds: ``none``, ``lagrange`` (Adam projected
ascent; MAPPO-Lag: per agent, SGD after every minibatch step) and ``pid`` (CPPO-PID).

Defaults are the Safety-Gymnasium paper's hyper-parameters (appendix table, also SafePO's CLI
defaults), per family; fields of :class:`~sg_torchrl.train.config.TrainConfig` that a row does not
set have one default for all:

* first order (PG, PPO, PPO-Lag, CPPO-PID, FOCOPS, CUP): Adam 3e-4 for the actor (linearly annealed)
  and both critics, 40 passes of minibatch 64, KL early stop at 0.02, clip 0.2;
* second order (NPG, TRPO, TRPO-Lag, RCPO, CPO, PCPO): trust region 0.01, conjugate gradient 15
  iterations with damping 0.1, line search 15 steps of fraction 0.8 (PCPO 200), critics Adam 1e-3
  for 10 passes of minibatch 128, no actor learning rate;
* multi agent (MAPPO, HAPPO, MAPPO-Lag, MACPO): 10,000 steps per update (episode length 1000 x 10
  simulators), Adam 5e-4 for actors and critics, 5 epochs of one minibatch (the whole batch), KL
  early stop 0.016, MAPPO-Lag's multiplier init 1e-5 and SGD step 0.78; MACPO: trust region 0.01,
  10 conjugate-gradient iterations, 10 line-search steps of fraction 0.5, 15 critic epochs. SafePO's
  settings the paper does not list: gradient-norm clip 10, no critic L2.

The off-policy family (SAC, TD3, DDPG, their Lagrangian and PID forms) is not in the paper; its defaults
are OmniSafe's (``configs/off-policy/SACLag.yaml``, ``TD3Lag.yaml``, ``DDPGLag.yaml``, ``*PID.yaml``; its
off-policy benchmark's settings): 2,000 steps per epoch from one simulator, one gradient step per env step
on a minibatch of 256 from a replay buffer of 1,000,000, random actions for the first 10,000 steps (SAC) or
25,000 (TD3, DDPG), ReLU [256, 256] actor and critics with Adam 3e-4 (PID rows: actor 1e-4), gradient-norm
clip 40 per network, Polyak 0.005, actor and target updates every second gradient step (DDPG every
step), SAC's alpha fixed at 0.2, TD3's exploration noise 0.1 and target smoothing 0.2 clipped at 0.5,
no observation normalisation, no critic L2; Lagrange init 0.001 with Adam 0.001; cost limit 25. Where
OmniSafe updates the multiplier after every gradient step from the last episodes' mean cost, ``sg-train``
updates it once per epoch from the epoch's, as for the on-policy family; so the PID rows keep the paper's
per-epoch gains (0.1 / 0.01 / 0.01, CPPO-PID's): OmniSafe's 1e-6 / 1e-7 / 1e-7 are sized for 2,000 updates
per epoch and would leave the multiplier where it starts.

Adding an algorithm adds a row here (and, for a new kind, its builder in :mod:`sg_torchrl.train`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

__all__ = [
    "AGENTS", "BASELINES", "ENTRIES", "FAMILIES", "MACPO_STEP_DEFAULTS", "MULTIPLIERS", "OFF_POLICY", "SECOND_ORDER",
    "UPDATES", "AlgorithmEntry",
    "UnknownAlgorithmError", "baseline", "get", "names", "resolve", "rows",
]

AGENTS = ("single", "multi")
FAMILIES = ("first_order", "second_order", "off_policy")
#: Update kinds: the first-order loops, the trust-region steps of the actor, the off-policy steps.
UPDATES = ("first_order", "two_stage", "natural", "trpo", "cpo", "pcpo", "off_policy")
MULTIPLIERS = ("none", "lagrange", "pid")


class UnknownAlgorithmError(KeyError, ValueError):
    """An algorithm name the manifest does not hold: a ``KeyError`` (a missing row) and a ``ValueError``
    (a bad ``algo`` value), whose message lists the known names."""

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0])


def resolve(path: str) -> Any:
    """The object a ``"package.module:Name"`` path names (imports the module)."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class AlgorithmEntry:
    """One algorithm: its ``--algo`` name, how the paper prints it, its kinds and its paper defaults.

    Attributes:
        name: the ``sg-train --algo`` value (and run directory component).
        title: the name as the Safety-Gymnasium paper and SafePO print it (``"PPO-Lag"``).
        agents: ``"single"`` or ``"multi"``.
        family: ``"first_order"``, ``"second_order"`` (the actor moves by a trust-region step, no actor
            learning rate) or ``"off_policy"`` (SAC, TD3, DDPG and their constrained forms: a replay buffer).
        update: the update kind (:data:`UPDATES`), which chooses the update builder.
        multiplier: the multiplier kind (:data:`MULTIPLIERS`), which chooses the multiplier builder.
        loss: the loss class as ``"module:Name"``, imported only by :meth:`loss_class`.
        loss_options: the loss's keyword arguments taken from the run's config, as ``{keyword: TrainConfig
            field}`` (``{"clip_epsilon": "clip_ratio"}``): the trainer builds every loss from its row alone.
        defaults: ``TrainConfig`` field values the paper gives this algorithm (read-only).
        step_options: second-order rows: the trust-region step's keyword arguments taken from the run's config,
            as ``{keyword: TrainConfig field}`` (PCPO's ``{"use_hx_direction": "pcpo_hx_direction"}``); the
            config refuses such a field, set away from its default, for a row that does not read it.
        round: multi-agent rows: the round class (``"module:Name"``) that updates the agents one at a time.
        paper_name: the row's name in the paper's results tables (``paper_results.csv``) when not ``title``.
    """

    name: str
    title: str
    agents: str
    family: str
    update: str
    multiplier: str
    loss: str
    defaults: Mapping[str, Any] = field(default_factory=dict, hash=False)
    loss_options: Mapping[str, str] = field(default_factory=dict, hash=False)
    step_options: Mapping[str, str] = field(default_factory=dict, hash=False)
    round: str | None = None
    paper_name: str | None = None

    def __post_init__(self) -> None:
        for attribute, allowed in (("agents", AGENTS), ("family", FAMILIES), ("update", UPDATES),
                                   ("multiplier", MULTIPLIERS)):
            if getattr(self, attribute) not in allowed:
                raise ValueError(f"algorithm {self.name!r}: {attribute} {getattr(self, attribute)!r} is not one of "
                                 f"{', '.join(allowed)}")
        if (self.round is None) == (self.agents == "multi"):
            raise ValueError(f"algorithm {self.name!r}: a round class is given for multi-agent rows only, and always")
        object.__setattr__(self, "defaults", MappingProxyType(dict(self.defaults)))
        if self.step_options and not self.second_order:
            raise ValueError(f"algorithm {self.name!r}: step options are for the trust-region (second-order) rows")
        for name in ("loss_options", "step_options"):
            object.__setattr__(self, name, MappingProxyType(dict(getattr(self, name))))

    @property
    def multi_agent(self) -> bool:
        return self.agents == "multi"

    @property
    def second_order(self) -> bool:
        return self.family == "second_order"

    @property
    def off_policy(self) -> bool:
        return self.family == "off_policy"

    @property
    def paper(self) -> str:
        """The row's name in the paper's results tables."""
        return self.paper_name or self.title

    def loss_class(self) -> type:
        """The loss class (imports torch)."""
        return resolve(self.loss)

    def round_class(self) -> type | None:
        """A multi-agent row's round class (imports torch); ``None`` for single-agent rows."""
        return resolve(self.round) if self.round else None


# ---------------------------------------------------------------------------- paper defaults
_SINGLE_AGENT_DEFAULTS = dict(
    env_id="SafetyHalfCheetahVelocity-v1", num_envs=10, steps_per_epoch=20_000, max_grad_norm=40.0, critic_l2=1e-3,
    lagrangian_init=1e-3, lagrangian_lr=0.035, cg_iters=15, step_fraction=0.8, normalize_obs=True,
)
_FIRST_ORDER_DEFAULTS = dict(_SINGLE_AGENT_DEFAULTS, actor_lr=3e-4, critic_lr=3e-4, update_iters=40, minibatch_size=64,
                             target_kl=0.02)
_SECOND_ORDER_DEFAULTS = dict(_SINGLE_AGENT_DEFAULTS, actor_lr=0.0, critic_lr=1e-3, update_iters=10,
                              minibatch_size=128, target_kl=0.01, line_search_steps=15)
# FOCOPS and CUP bound their multiplier nu by 2.0 (the table's "nu 2.00"; SafePO's CUP script uses 0.2,
# compared on PointGoal1 in benchmarks/RESULTS.md).
_BOUNDED_NU_DEFAULTS = dict(_FIRST_ORDER_DEFAULTS, multiplier_upper_bound=2.0)
# Paper, multi-agent rows (10,000 steps per update from 10 simulators of 1000-step episodes, one
# minibatch: ``minibatch_size`` at least the batch); SafePO's multi-agent scripts for what the paper
# does not list (gradient clip 10 per network, critics without L2). Observation normalisation stands
# in for the input LayerNorm of SafePO's networks (see sg_torchrl.train.config).
_MULTI_AGENT_DEFAULTS = dict(
    env_id="Safety2x3HalfCheetahVelocity-v0", num_envs=10, steps_per_epoch=10_000, actor_lr=5e-4, critic_lr=5e-4, update_iters=5,
    minibatch_size=10_000, target_kl=0.016, max_grad_norm=10.0, critic_l2=0.0, lagrangian_init=1e-5,
    lagrangian_lr=0.78, cg_iters=15, step_fraction=0.8, normalize_obs=True,
)
#: MACPO's trust-region step, the one home of its defaults (read by
#: :class:`~sg_torchrl.objectives.multi_agent.MACPORule`; the first four are also the macpo row's config
#: values): the paper's trust region 0.01, CG 10 and 10 search steps of 0.5; SafePO's cap of 0.5 on the
#: direction's norm and 0.1 of it tried first (``fraction_coef``).
MACPO_STEP_DEFAULTS: Mapping[str, Any] = MappingProxyType(dict(
    target_kl=0.01, cg_iters=10, line_search_steps=10, step_fraction=0.5, max_step_norm=0.5, initial_step_fraction=0.1,
))
# MACPO: its step's config fields and 15 critic epochs ("SGD iters").
_MACPO_DEFAULTS = dict(_MULTI_AGENT_DEFAULTS, actor_lr=0.0, update_iters=15,
                       **{name: MACPO_STEP_DEFAULTS[name] for name in ("target_kl", "cg_iters", "line_search_steps",
                                                                       "step_fraction")})

# OmniSafe's off-policy settings (module docstring); the on-policy fields they leave unused keep the
# single-agent values so that every config validates alike.
_OFF_POLICY_DEFAULTS = dict(
    _SINGLE_AGENT_DEFAULTS, steps_per_epoch=2_000, num_envs=1, actor_lr=3e-4, critic_lr=3e-4, critic_l2=0.0,
    minibatch_size=256, update_iters=1, target_kl=0.02, normalize_obs=False, lagrangian_lr=1e-3, replay_size=1_000_000,
    warmup_steps=25_000, polyak=0.005, policy_delay=2, utd_ratio=1.0, exploration_noise=0.1, policy_noise=0.2,
    noise_clip=0.5, alpha=0.2, cost_critic_reduction="max",
)
_SAC_DEFAULTS = dict(_OFF_POLICY_DEFAULTS, warmup_steps=10_000)
_DDPG_DEFAULTS = dict(_OFF_POLICY_DEFAULTS, policy_delay=1)

# ---------------------------------------------------------------------------- the rows
_PG_LOSS = "sg_torchrl.objectives:PGLoss"
_PPO_LAG_LOSS = "sg_torchrl.objectives:PPOLagLoss"
_AGENT_LOSS = "sg_torchrl.objectives.multi_agent:AgentPPOLoss"
_ROUNDS = "sg_torchrl.train.multi_agent_updates:"


#: The first-order losses' options from the config (clip and critic L2; the subclasses add their own).
_PPO_OPTIONS = {"clip_epsilon": "clip_ratio", "critic_l2_coeff": "critic_l2"}


def _single(name: str, title: str, family: str, update: str, multiplier: str, loss: str,
            defaults: Mapping[str, Any], step_options: Mapping[str, str] | None = None,
            **loss_options: str) -> AlgorithmEntry:
    options = {**_PPO_OPTIONS, **loss_options} if loss != _PG_LOSS else {"critic_l2_coeff": "critic_l2"}
    return AlgorithmEntry(name, title, "single", family, update, multiplier, loss, defaults, options,
                          step_options or {})


def _multi(name: str, title: str, family: str, update: str, multiplier: str, round_name: str,
           defaults: Mapping[str, Any]) -> AlgorithmEntry:
    return AlgorithmEntry(name, title, "multi", family, update, multiplier, _AGENT_LOSS, defaults,
                          round=_ROUNDS + round_name)


def _off(name: str, title: str, multiplier: str, loss: str, defaults: Mapping[str, Any],
         **loss_options: str) -> AlgorithmEntry:
    """An off-policy row: its loss from ``sg_torchrl.objectives.off_policy``; the PID rows' actor rate OmniSafe's."""
    if multiplier == "pid":
        defaults = dict(defaults, actor_lr=1e-4)
    return AlgorithmEntry(name, title, "single", "off_policy", "off_policy", multiplier,
                          "sg_torchrl.objectives.off_policy:" + loss, defaults,
                          {"cost_reduction": "cost_critic_reduction", **loss_options})


_SAC_OPTIONS = {"alpha_init": "alpha"}
_TD3_OPTIONS = {"policy_noise": "policy_noise", "noise_clip": "noise_clip"}
_FIRST, _SECOND, _OFF = FAMILIES
#: Every algorithm, in the paper's order (its tables' rows): single agent, then multi agent.
ENTRIES: tuple[AlgorithmEntry, ...] = (
    _single("pg", "PG", _FIRST, "first_order", "none", _PG_LOSS, _FIRST_ORDER_DEFAULTS),
    _single("ppo", "PPO", _FIRST, "first_order", "none", _PPO_LAG_LOSS, _FIRST_ORDER_DEFAULTS),
    _single("ppo_lag", "PPO-Lag", _FIRST, "first_order", "lagrange", _PPO_LAG_LOSS, _FIRST_ORDER_DEFAULTS),
    _single("cppo_pid", "CPPO-PID", _FIRST, "first_order", "pid", _PPO_LAG_LOSS, _FIRST_ORDER_DEFAULTS),
    _single("focops", "FOCOPS", _FIRST, "first_order", "lagrange", "sg_torchrl.objectives:FOCOPSLoss",
            _BOUNDED_NU_DEFAULTS, temperature="focops_temperature", target_kl="target_kl",
            safepo_broadcast="focops_safepo_broadcast"),
    _single("cup", "CUP", _FIRST, "two_stage", "lagrange", "sg_torchrl.objectives:CUPLoss", _BOUNDED_NU_DEFAULTS,
            gamma="gamma", cup_lambda="cup_lambda"),
    # Second order: PPO-Lag's critic losses, a trust-region step for the actor. RCPO, as SafePO
    # implements it, is NPG with a Lagrange multiplier; TRPO-Lag is TRPO with one.
    _single("npg", "NPG", _SECOND, "natural", "none", _PPO_LAG_LOSS, _SECOND_ORDER_DEFAULTS),
    _single("trpo", "TRPO", _SECOND, "trpo", "none", _PPO_LAG_LOSS, _SECOND_ORDER_DEFAULTS),
    _single("trpo_lag", "TRPO-Lag", _SECOND, "trpo", "lagrange", _PPO_LAG_LOSS, _SECOND_ORDER_DEFAULTS),
    _single("rcpo", "RCPO", _SECOND, "natural", "lagrange", _PPO_LAG_LOSS, _SECOND_ORDER_DEFAULTS),
    _single("cpo", "CPO", _SECOND, "cpo", "none", _PPO_LAG_LOSS, _SECOND_ORDER_DEFAULTS),
    # PCPO: the paper's reward step H^-1 g by default; ``--pcpo-hx-direction true`` takes SafePO's H x.
    _single("pcpo", "PCPO", _SECOND, "pcpo", "none", _PPO_LAG_LOSS,
            dict(_SECOND_ORDER_DEFAULTS, line_search_steps=200), {"use_hx_direction": "pcpo_hx_direction"}),
    # Beyond the paper: PPO-Lag with the cost term clipped apart and pessimistically (README, "Add an
    # algorithm": one Surrogate, one loss subclass and this row).
    _single("ppo_lag_pessimistic", "PPO-Lag-Pessimistic", _FIRST, "first_order", "lagrange",
            "sg_torchrl.objectives:PessimisticPPOLagLoss", _FIRST_ORDER_DEFAULTS),
    # Beyond the paper: the off-policy family (OmniSafe's SAC, TD3, DDPG and their Lagrangian and PID forms).
    *(_off(f"{base}{suffix}", f"{title}{label}", multiplier, loss, defaults, **options)
      for suffix, label, multiplier in (("", "", "none"), ("_lag", "-Lag", "lagrange"), ("_pid", "-PID", "pid"))
      for base, title, loss, defaults, options in (
          ("sac", "SAC", "SACLagLoss", _SAC_DEFAULTS, _SAC_OPTIONS),
          ("td3", "TD3", "TD3LagLoss", _OFF_POLICY_DEFAULTS, _TD3_OPTIONS),
          ("ddpg", "DDPG", "DDPGLagLoss", _DDPG_DEFAULTS, {}))),
    _multi("mappo", "MAPPO", _FIRST, "first_order", "none", "MAPPOUpdate", _MULTI_AGENT_DEFAULTS),
    _multi("happo", "HAPPO", _FIRST, "first_order", "none", "HAPPOUpdate", _MULTI_AGENT_DEFAULTS),
    _multi("mappo_lag", "MAPPO-Lag", _FIRST, "first_order", "lagrange", "MAPPOLagUpdate", _MULTI_AGENT_DEFAULTS),
    _multi("macpo", "MACPO", _SECOND, "cpo", "none", "MACPOUpdate", _MACPO_DEFAULTS),
)
_BY_NAME = {entry.name: entry for entry in ENTRIES}
assert len(_BY_NAME) == len(ENTRIES), "two rows share a name"

#: The unconstrained algorithm the paper normalises J^R by, per ``agents`` (PPO's, MAPPO's).
BASELINES: Mapping[str, str] = MappingProxyType({"single": "ppo", "multi": "mappo"})


def _check(value: str | None, allowed: tuple[str, ...], what: str) -> None:
    if value is not None and value not in allowed:
        raise ValueError(f"{what} must be one of {', '.join(allowed)} (or None), got {value!r}")


def rows(agents: str | None = None, family: str | None = None) -> tuple[AlgorithmEntry, ...]:
    """The rows, in the paper's order, of ``agents`` (``"single"`` / ``"multi"``) and ``family`` when given."""
    _check(agents, AGENTS, "agents")
    _check(family, FAMILIES, "family")
    return tuple(entry for entry in ENTRIES
                 if agents in (None, entry.agents) and family in (None, entry.family))


def names(agents: str | None = None, family: str | None = None) -> tuple[str, ...]:
    """The names of :func:`rows`' rows (``names(agents="multi")`` -> ``("mappo", "happo", "mappo_lag", "macpo")``)."""
    return tuple(entry.name for entry in rows(agents, family))


def get(name: str) -> AlgorithmEntry:
    """The row of ``name``.

    Raises:
        UnknownAlgorithmError: no such row; the message lists the known names.
    """
    try:
        return _BY_NAME[name]
    except (KeyError, TypeError):  # TypeError: an unhashable value
        raise UnknownAlgorithmError(f"unknown algorithm {name!r}; known: {', '.join(_BY_NAME)}") from None


def baseline(name: str) -> str:
    """The algorithm whose J^R the paper normalises ``name``'s by: MAPPO for a multi-agent one, else PPO."""
    entry = _BY_NAME.get(name)
    return BASELINES[entry.agents if entry is not None else "single"]


#: Algorithms whose actor moves by a trust-region step (no actor learning rate).
SECOND_ORDER: frozenset[str] = frozenset(names(family="second_order"))
#: The off-policy algorithms (a replay buffer; :mod:`sg_torchrl.train.off_policy`).
OFF_POLICY: frozenset[str] = frozenset(names(family="off_policy"))
