"""Typed configuration of one ``sg-train`` experiment, overridable from the command line.

Defaults are the Safety-Gymnasium paper's hyper-parameters (appendix table, also SafePO's CLI
defaults): 20,000 steps per epoch from 10 simulators, gamma 0.99, GAE lambda 0.95 for reward and
cost, critic L2 1e-3, gradient-norm clip 40, Lagrange init 0.001 / lr 0.035, PID gains 0.1 / 0.01 /
0.01, cost limit 25. Fields whose paper value depends on the algorithm family default to ``None``
and are filled from :data:`ALGORITHM_DEFAULTS` when the config is built: the rows' defaults of the
algorithm manifest (:mod:`sg_torchrl.algorithms.manifest`, which lists them per family), the one place
that names the algorithms. Multi-agent runs (:mod:`sg_torchrl.train.multi_agent_group`) use MLP [128, 128]
and normalise observations (running mean / std per agent and feature, and of the state): SafePO feeds
raw observations to networks that start with a LayerNorm of their input, ours (TorchRL's
``MultiAgentMLP``) have none, and on raw Humanoid observations their initial action means reach tens
(control cost dominates the reward).

Pixel observations (a ``...Vision-v0`` id, or ``env_options`` ``obs_mode=rgb|rgbd|vector+rgb|
vector+rgbd``) need no option: the single-agent networks read whatever the env's observation spec
holds, with a CNN encoder before ``hidden_sizes`` when there are images
(:mod:`sg_torchrl.modules.mlp`), and ``normalize_obs`` applies to the flat vector only. The
``vision`` preset is PPO-Lag on ``SafetyPointGoal1Vision-v0`` sized for a CPU: pixels only, 64 x 64
(``env_options``; the Vision ids default to the vector and a 256 x 256 image, Safety-Gymnasium's layout).

**Seed groups.** ``seeds`` (``--seeds 0 1 2``) trains S seeds side by side in one process, each
exactly as its single-seed run with that ``seed`` would train: ``num_envs``, ``steps_per_epoch`` and
``total_steps`` are per seed. ``--seeds 0`` is a group of one; ``--seed`` and ``--seeds`` together are
refused. Groups train every single-agent algorithm (first and second order; networks stacked,
:mod:`sg_torchrl.train.seed_group`), on flat-vector or pixel
observations, and the four multi-agent ones (one round per seed,
:mod:`sg_torchrl.train.multi_agent_group`), on flat-vector observations. One seed (``seed``) trains on
the same engine and family class as a group of that one seed, writing a single run's layout (:attr:`group`
picks the layout, :func:`~sg_torchrl.train.seed_runs.run_layout`).

A multi-agent algorithm needs a multi-agent env id (``Safety2x3HalfCheetahVelocity-v0``, ...) and
a single-agent algorithm a single-agent id; :meth:`TrainConfig.validate` says so when they do not
match.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_type_hints

from sg_torchrl.algorithms import manifest
from sg_torchrl.train.devices import check_device_name
from sg_torchrl.train.presets import PRESETS
from sg_torchrl.train.writes import check_run_name, write_atomic
from sg_torchrl.validation import describe, fits

__all__ = [
    "ALGORITHM_DEFAULTS", "ALGORITHM_NAMES", "MULTI_AGENT_ALGORITHM_NAMES", "OFF_POLICY_ALGORITHM_NAMES",
    "OFF_POLICY_FIELDS", "RETIRED_FIELDS", "SECOND_ORDER", "STEP_OPTION_FIELDS", "VARIANT_FIELDS",
    "TrainConfig", "PRESETS",
]

#: Fields that configs saved by earlier versions hold and this one reads past: ``engine`` chose between the
#: seed-group engine (``"fused"``, the only one now) and the retired ``LossModule`` trainer (``"loss-module"``,
#: whose checkpoints ``sg-train --resume`` refuses).
RETIRED_FIELDS: tuple[str, ...] = ("engine",)
# Views of the algorithm manifest (sg_torchrl.algorithms.manifest), kept for the code that imports them here.
#: The single-agent on-policy algorithms (rows of :data:`sg_torchrl.train.algorithms.ALGORITHMS`).
ALGORITHM_NAMES: tuple[str, ...] = tuple(n for n in manifest.names(agents="single") if n not in manifest.OFF_POLICY)
#: The off-policy algorithms (:mod:`sg_torchrl.train.off_policy`).
OFF_POLICY_ALGORITHM_NAMES: tuple[str, ...] = manifest.names(family="off_policy")
#: Fields only the off-policy algorithms read (``None`` for the others, which refuse a value).
OFF_POLICY_FIELDS: tuple[str, ...] = ("replay_size", "warmup_steps", "polyak", "policy_delay", "utd_ratio",
                                      "exploration_noise", "policy_noise", "noise_clip", "alpha",
                                      "cost_critic_reduction")
#: Fields a trust-region step reads through a manifest row's ``step_options`` (refused, set, for other rows).
STEP_OPTION_FIELDS: tuple[str, ...] = tuple(sorted({name for entry in manifest.rows()
                                                   for name in entry.step_options.values()}))
#: Switches to one row's SafePO variant: its step options and loss switches (refused, set, for other rows).
VARIANT_FIELDS: tuple[str, ...] = STEP_OPTION_FIELDS + ("focops_safepo_broadcast",)
#: The multi-agent algorithms (rows of :data:`sg_torchrl.train.multi_agent.MULTI_AGENT_ALGORITHMS`).
MULTI_AGENT_ALGORITHM_NAMES: tuple[str, ...] = manifest.names(agents="multi")
#: Algorithms whose actor moves by a trust-region step (no actor learning rate).
SECOND_ORDER = manifest.SECOND_ORDER
#: The paper's hyper-parameters per algorithm (the manifest rows' ``defaults``; a fresh copy here).
#: Fields not listed have one default for all.
ALGORITHM_DEFAULTS: dict[str, dict[str, Any]] = {entry.name: dict(entry.defaults) for entry in manifest.rows()}


def _opt(default: Any, help: str, **kwargs: Any) -> Any:
    if isinstance(default, dict):
        return field(default_factory=lambda: dict(default), metadata={"help": help, **kwargs})
    if isinstance(default, (list, tuple)):
        return field(default_factory=lambda: list(default), metadata={"help": help, **kwargs})
    return field(default=default, metadata={"help": help, **kwargs})


@dataclass
class TrainConfig:
    """One experiment. Every field is a command-line flag (``--total-steps 200000``)."""

    algo: str = _opt("ppo_lag", f"safe RL algorithm ({', '.join(MULTI_AGENT_ALGORITHM_NAMES)}: multi-agent)",
                     choices=manifest.names())
    env_id: str | None = _opt(
        None, "Safety-Gymnasium env id (sg_torchrl.list_envs()); default SafetyHalfCheetahVelocity-v1, for "
        "multi-agent algorithms Safety2x3HalfCheetahVelocity-v0")
    env_options: dict[str, Any] = _opt(
        {}, "task options for sg_torchrl.make as KEY=VALUE (e.g. velocity_threshold=1.5 cost_mode=raw "
        "lidar=natural); values are read as JSON where they parse, else as strings")
    seed: int | None = _opt(
        None, "seed of the simulators, the networks and the minibatch order (with seeds: the first of them)",
        shown_default=0)
    seeds: list[int] = _opt(
        (), "train a seed group: these seeds side by side in one process (e.g. 0 1 2), each exactly as its "
        "single-seed run; num_envs, steps_per_epoch and total_steps are per seed; logs go to seed-XXX/ in the "
        "group's directory; every algorithm; single-agent ones on flat or pixel observations")
    total_steps: int = _opt(1_000_000, "env steps to train for (all simulators together)")
    num_envs: int | None = _opt(None, "simulators stepped in one process (10; off-policy 1, OmniSafe's)",
                                shown_default=10)
    steps_per_epoch: int | None = _opt(
        None, "env steps per epoch (one policy update), a multiple of num_envs (20000; multi-agent 10000)")
    cost_limit: float = _opt(25.0, "episode cost limit d of the constrained MDP")
    gamma: float = _opt(0.99, "discount of reward and cost")
    gae_lambda: float = _opt(0.95, "GAE lambda of the reward advantage")
    cost_gae_lambda: float = _opt(0.95, "GAE lambda of the cost advantage")
    hidden_sizes: list[int] = _opt(
        (), "hidden layer sizes of actor and critics; default: the paper's, tanh 256 256 for the Ant and "
        "Doggo navigation robots, else tanh 64 64; multi-agent: ReLU 128 128; off-policy: ReLU 256 256")
    actor_lr: float | None = _opt(
        None, "actor Adam learning rate (first order: 3e-4, linearly annealed to 0; multi-agent 5e-4, constant)")
    critic_lr: float | None = _opt(
        None, "reward and cost critic Adam learning rate (first order 3e-4, second 1e-3, multi-agent 5e-4)")
    update_iters: int | None = _opt(
        None, "passes over the epoch's data (first order 40, second order 10 critic passes; multi-agent 5 epochs "
        "per agent, MACPO 15 critic epochs)")
    minibatch_size: int | None = _opt(
        None, "samples per gradient step (first order 64, second order 128; multi-agent 10000: the whole batch)")
    clip_ratio: float = _opt(0.2, "PPO ratio clip epsilon")
    target_kl: float | None = _opt(
        None, "first order: stop the passes once KL(old || new) exceeds this (0.02; multi-agent 0.016, per "
        "agent); second order: the trust region delta (0.01)")
    max_grad_norm: float | None = _opt(
        None, "gradient-norm clip: global over actor and critics (40); multi-agent per network (10)")
    critic_l2: float | None = _opt(None, "L2 penalty on critic weights (1e-3; multi-agent 0)")
    lagrangian_init: float | None = _opt(
        None, "initial Lagrange multiplier (1e-3; PID: initial integral; MAPPO-Lag 1e-5, one per agent)")
    lagrangian_lr: float | None = _opt(
        None, "Lagrange multiplier learning rate (Adam 0.035; MAPPO-Lag: SGD 0.78 after every minibatch step)")
    pid_kp: float = _opt(0.1, "CPPO-PID proportional gain")
    pid_ki: float = _opt(0.01, "CPPO-PID integral gain")
    pid_kd: float = _opt(0.01, "CPPO-PID derivative gain")
    pid_d_delay: int = _opt(10, "CPPO-PID derivative delay (epochs)")
    multiplier_upper_bound: float | None = _opt(None, "cap of the Lagrange multiplier (FOCOPS and CUP: 2.0)")
    focops_temperature: float = _opt(1.5, "FOCOPS temperature lambda")
    focops_safepo_broadcast: bool = _opt(
        False, "FOCOPS: SafePO's loss, whose trust-region indicator scales the advantage term by the batch's "
        "in-region fraction, instead of the FOCOPS paper's per-sample mask")
    cup_lambda: float = _opt(0.95, "CUP's GAE-style lambda in the projection factor (1 - gamma lambda) / (1 - gamma)")
    cg_iters: int | None = _opt(None, "second order: conjugate-gradient iterations (15; MACPO 10)")
    cg_damping: float = _opt(0.1, "second order: damping added to the Fisher-vector product")
    line_search_steps: int | None = _opt(
        None, "second order: backtracking steps (15; PCPO 200; MACPO 10; NPG/RCPO none)")
    pcpo_hx_direction: bool = _opt(
        False, "PCPO: take SafePO's reward step, the Fisher product H x of the natural gradient x (about the plain "
        "gradient) at the natural step's length, instead of the PCPO paper's x = H^-1 g")
    step_fraction: float | None = _opt(None, "second order: backtracking shrink factor (0.8; MACPO 0.5)")
    normalize_obs: bool | None = _opt(
        None, "running mean/std observation normalisation (default on; of the flat vector only, images are scaled "
        "in the networks; multi-agent: each agent's observation, per agent, and the global state)")
    eval_episodes: int = _opt(10, "deterministic evaluation episodes at the end (0 disables)")
    output_dir: str = _opt("runs", "root folder of run directories")
    run_name: str | None = _opt(
        None, "run directory name inside output_dir, '/' for nested folders; absolute paths and '..' are refused "
        "(default: <env>/<algo>/seed-<seed>; a seed group: <env>/<algo>/seeds-0-1-2)")
    wandb: Literal["offline", "online", "disabled"] = _opt("offline", "wandb mode; offline needs no account")
    checkpoint_every: int = _opt(
        10, "epochs between checkpoints; the first epoch a process trains and the last epoch are always saved")
    checkpoint_minutes: float = _opt(
        1.0, "also checkpoint after an epoch that ends this many minutes or more after the last checkpoint (0: "
        "every epoch); a SIGKILL loses at most the epoch under way and the epochs finished since the last "
        "checkpoint, which all ended within this many minutes of it")
    resume: str | None = _opt(
        None, "checkpoint file or run directory to continue; the run continues in that directory, whatever its "
        "saved config's output_dir / run_name, with the saved config and the flags given here")
    overwrite: bool = _opt(
        False, "start over in a run directory that already holds a run (removes its checkpoint and logs); "
        "without it a new run refuses such a directory", bare_flag=True)
    progress: bool = _opt(True, "show a progress bar")
    threads: int = _opt(1, "torch threads (1 is fastest for small MLPs on few cores)")
    compile: bool = _opt(
        False, "single-agent: torch.compile the minibatch losses (about 2x faster first-order updates on a CPU after "
        "tens of seconds of compiling; same algorithm, float rounding differs from eager)")
    # Off-policy algorithms (sac, td3, ddpg, *_lag, *_pid) only; OmniSafe's defaults from the manifest.
    replay_size: int | None = _opt(None, "off-policy: replay buffer capacity per seed (1000000)")
    warmup_steps: int | None = _opt(
        None, "off-policy: env steps of uniformly random actions before the first gradient step (SAC 10000, TD3 and "
        "DDPG 25000)")
    polyak: float | None = _opt(None, "off-policy: target networks move this fraction towards the trained ones (0.005)")
    policy_delay: int | None = _opt(
        None, "off-policy: gradient steps per actor and target update (SAC and TD3 2, DDPG 1)")
    utd_ratio: float | None = _opt(None, "off-policy: gradient steps per env step, per seed (1.0)")
    exploration_noise: float | None = _opt(None, "TD3 / DDPG: std of the Gaussian noise added to actions (0.1)")
    policy_noise: float | None = _opt(None, "TD3: std of the target policy smoothing noise (0.2)")
    noise_clip: float | None = _opt(None, "TD3: clip of the target policy smoothing noise (0.5)")
    alpha: float | None = _opt(None, "SAC: the fixed entropy weight (0.2)")
    cost_critic_reduction: Literal["max", "mean", "min"] | None = _opt(
        None, "off-policy: reduction of the twin cost critics (max: pessimistic for cost)")
    device: str = _opt(
        "cpu", "where the networks, optimiser state and updates live: cpu, cuda or cuda:N (the simulators stay on "
        "their backend; a resumed run may change it)")

    def __post_init__(self) -> None:
        for name, value in ALGORITHM_DEFAULTS.get(self.algo, {}).items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.seed is None:  # a group's seed is its first seed; bad seeds are refused by validate()
            seeds = self.seeds
            self.seed = seeds[0] if isinstance(seeds, list) and seeds and type(seeds[0]) is int else 0
        self.validate()

    def keyword_options(self, fields: Mapping[str, str]) -> dict[str, Any]:
        """A manifest row's ``loss_options`` or ``step_options`` (``{keyword: field}``) read from this config."""
        return {keyword: getattr(self, name) for keyword, name in fields.items()}

    @property
    def second_order(self) -> bool:
        """Whether the actor moves by a trust-region step (NPG, TRPO, TRPO-Lag, RCPO, CPO, PCPO, MACPO)."""
        return self.algo in SECOND_ORDER

    @property
    def group(self) -> bool:
        """Whether this is a seed group (``seeds`` given), in a group's layout (:mod:`sg_torchrl.train.seed_runs`)."""
        return bool(self.seeds)

    @property
    def multi_agent(self) -> bool:
        """Whether the algorithm is one of the multi-agent ones (MAPPO, HAPPO, MAPPO-Lag, MACPO)."""
        return self.algo in MULTI_AGENT_ALGORITHM_NAMES

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        names = manifest.names()
        if self.algo not in names:
            raise ValueError(f"config: unknown algo {self.algo!r}; choose from {', '.join(names)}")
        self._validate_types()
        self._validate_env_kind()
        self._validate_seeds()
        self._validate_off_policy()
        self._validate_variant_options()
        self._validate_device()
        positive = ("total_steps", "num_envs", "steps_per_epoch", "update_iters", "minibatch_size", "pid_d_delay",
                    "cg_iters", "line_search_steps", "threads")
        for name in positive:
            if getattr(self, name) is not None and getattr(self, name) < 1:  # None: unused by this algorithm
                raise ValueError(f"config: {name} must be >= 1, got {getattr(self, name)}")
        for name in ("seed", "eval_episodes"):
            if getattr(self, name) < 0:
                raise ValueError(f"config: {name} must be >= 0, got {getattr(self, name)}")
        if not self.second_order and not self.actor_lr > 0:
            raise ValueError(f"config: actor_lr must be > 0, got {self.actor_lr}")
        if not 0.0 < self.step_fraction < 1.0:
            raise ValueError(f"config: step_fraction must be in (0, 1), got {self.step_fraction}")
        for name in ("critic_lr", "lagrangian_lr", "target_kl", "max_grad_norm", "clip_ratio", "focops_temperature"):
            if not getattr(self, name) > 0:
                raise ValueError(f"config: {name} must be > 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda", "cost_gae_lambda", "cup_lambda"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"config: {name} must be in [0, 1], got {getattr(self, name)}")
        if self.cost_limit < 0:
            raise ValueError(f"config: cost_limit must be >= 0, got {self.cost_limit}")
        if self.steps_per_epoch % self.num_envs:
            raise ValueError(
                f"config: steps_per_epoch ({self.steps_per_epoch}) must be a multiple of num_envs ({self.num_envs})"
            )
        if self.total_steps < self.steps_per_epoch:
            raise ValueError(
                f"config: total_steps ({self.total_steps}) is less than one epoch ({self.steps_per_epoch})"
            )
        if self.total_steps % self.steps_per_epoch:  # training runs whole epochs: the rest would be dropped
            lower = self.total_steps - self.total_steps % self.steps_per_epoch
            raise ValueError(
                f"config: total_steps ({self.total_steps}) is not a multiple of steps_per_epoch "
                f"({self.steps_per_epoch}); training runs whole epochs and would stop at {lower}: give total_steps "
                f"{lower} or {lower + self.steps_per_epoch}"
            )
        if self.cg_damping < 0 or (self.multiplier_upper_bound is not None and self.multiplier_upper_bound < 0):
            raise ValueError("config: cg_damping and multiplier_upper_bound must be >= 0")
        if self.hidden_sizes and min(self.hidden_sizes) < 1:
            raise ValueError(f"config: hidden_sizes must be positive, got {self.hidden_sizes}")
        if self.compile and self.multi_agent:
            raise ValueError(
                f"config: compile applies to the single-agent minibatch losses; {self.algo!r} updates each agent on "
                f"the whole batch at once, where the matrix products dominate and compiling gains nothing (a compiled "
                f"MAPPO-Lag round of 8 seeds measured 3 % less CPU per env step, within the noise)"
            )
        self._validate_env_options()
        self._validate_observation_mode()
        self._validate_checkpointing()
        if self.run_name is not None:  # every file of the run stays inside output_dir
            check_run_name(self.run_name)

    def _validate_seeds(self) -> None:
        """A seed group's seeds: distinct, >= 0 and agreeing with ``seed`` (every algorithm trains in groups)."""
        if not self.seeds:
            return
        if min(self.seeds) < 0:
            raise ValueError(f"config: seeds must be >= 0, got {self.seeds}")
        repeated = sorted({s for s in self.seeds if self.seeds.count(s) > 1})
        if repeated:
            raise ValueError(f"config: seeds must be distinct (a repeated seed trains the same run twice), "
                             f"{', '.join(map(str, repeated))} repeated in {self.seeds}")
        if self.seed != self.seeds[0]:
            raise ValueError(f"config: seed ({self.seed}) and seeds ({self.seeds}) disagree: a seed group's seed is "
                             f"its first seed; give seeds alone")

    @property
    def off_policy(self) -> bool:
        """Whether the algorithm is an off-policy one (SAC, TD3, DDPG and their constrained forms)."""
        return self.algo in OFF_POLICY_ALGORITHM_NAMES

    def _validate_off_policy(self) -> None:
        """The off-policy fields: refused for the on-policy algorithms, in range for the off-policy ones."""
        if not self.off_policy:
            given = [name for name in OFF_POLICY_FIELDS if getattr(self, name) is not None]
            if given:
                raise ValueError(f"config: {given[0]} is an option of the off-policy algorithms "
                                 f"({', '.join(OFF_POLICY_ALGORITHM_NAMES)}), not of {self.algo!r}")
            return
        for name in ("replay_size", "policy_delay"):
            if getattr(self, name) < 1:
                raise ValueError(f"config: {name} must be >= 1, got {getattr(self, name)}")
        if self.warmup_steps < 0:
            raise ValueError(f"config: warmup_steps must be >= 0, got {self.warmup_steps}")
        if not 0.0 < self.polyak <= 1.0:
            raise ValueError(f"config: polyak must be in (0, 1], got {self.polyak}")
        if not self.utd_ratio > 0:
            raise ValueError(f"config: utd_ratio must be > 0, got {self.utd_ratio}")
        for name in ("exploration_noise", "policy_noise", "noise_clip", "alpha"):
            if getattr(self, name) < 0:
                raise ValueError(f"config: {name} must be >= 0, got {getattr(self, name)}")
        if self.observation_mode != "vector":
            raise ValueError(f"config: the off-policy algorithms train on flat-vector observations only; {self.env_id} "
                             f"with obs_mode={self.observation_mode!r} emits images")
        if self.normalize_obs:
            raise ValueError("config: the off-policy algorithms take no observation normalisation (OmniSafe's "
                             "default; a running normaliser would shift the replayed observations)")
        if self.compile:
            raise ValueError("config: --compile applies to the on-policy algorithms; the off-policy steps run eagerly")

    def _validate_variant_options(self) -> None:
        """A variant switch (:data:`VARIANT_FIELDS`) set for a row that does not read it: refused, never ignored."""
        def reads(row) -> set[str]:
            return {*row.step_options.values(), *row.loss_options.values()}

        for name in VARIANT_FIELDS:
            changed = getattr(self, name) != self.__dataclass_fields__[name].default
            if changed and name not in reads(manifest.get(self.algo)):
                readers = [row.name for row in manifest.ENTRIES if name in reads(row)]
                raise ValueError(f"config: {name} is an option of {', '.join(readers)}, not of {self.algo!r}")

    def _validate_device(self) -> None:
        """``device``'s form (:func:`~sg_torchrl.train.devices.check_device_name`), for every family. Whether this
        machine has the device is checked where training starts
        (:func:`~sg_torchrl.train.devices.check_device_available`), so a saved config reads anywhere."""
        check_device_name(self.device)

    def _validate_checkpointing(self) -> None:
        """Checkpoint intervals, and ``resume`` with ``overwrite`` (continue or start over: not both)."""
        if not (isinstance(self.checkpoint_every, int) and self.checkpoint_every >= 1):
            raise ValueError(f"config: checkpoint_every must be an integer >= 1, got {self.checkpoint_every!r}")
        if not (isinstance(self.checkpoint_minutes, (int, float)) and 0 <= self.checkpoint_minutes < float("inf")):
            raise ValueError(f"config: checkpoint_minutes must be a number >= 0, got {self.checkpoint_minutes!r}")
        if self.resume and self.overwrite:
            raise ValueError("config: resume continues a run and overwrite starts one over; give one of them")

    def _validate_types(self) -> None:
        """Every field holds a value of its annotated type, strictly (:mod:`sg_torchrl.validation`): a bool
        field ``True`` / ``False`` (not the truthy string ``"no"``), an int field an integer (not a bool), a
        float field a finite number (a NaN limit or rate compares false with everything and silently
        disables what it bounds). String fields take any value: paths may be ``pathlib.Path``."""
        hints = get_type_hints(TrainConfig)
        for f in dataclasses.fields(self):
            hint, value = hints[f.name], getattr(self, f.name)
            if hint not in (str, str | None) and not fits(hint, value):
                raise ValueError(f"config: {f.name} must be {describe(hint)}, got {value!r}")

    def _validate_env_options(self) -> None:
        """``env_options`` must be options the env id takes, of the types its constructor annotates: the
        check ``sg_torchrl.make`` runs (``sg_torchrl.envs.registry.validate_env_options``), run here so
        that a bad option fails before anything is built."""
        from sg_torchrl.envs.registry import validate_env_options

        if "device" in self.env_options:
            raise ValueError("config: env_options cannot set device: the simulators run on their backend (the "
                             "backend option); --device places the networks and updates")
        reserved = sorted(set(self.env_options) & {"num_envs", "seed"})
        if reserved:
            raise ValueError(
                f"config: env_options cannot set {', '.join(reserved)}; use --{reserved[0].replace('_', '-')}"
            )
        try:
            validate_env_options(self.env_id, self.env_options)
        except ValueError as error:  # InvalidEnvOptionError, naming the option and the env id
            raise ValueError(f"config: env_options: {error}") from None

    def _validate_observation_mode(self) -> None:
        """Pixel observations (a Vision id, or ``obs_mode`` with ``rgb`` / ``rgbd``) train through CNN
        encoders (:mod:`sg_torchrl.modules.mlp`), whose convolutions need images of at least
        ``DEFAULT_CNN.min_image_size`` (36) pixels a side; say so here rather than deep in the first
        forward pass. ``obs_mode`` and ``image_size`` are valid values here (:meth:`_validate_env_options`)."""
        from sg_torchrl.envs.registry import registry_entry

        obs_mode, image_size = self.observation_mode, {**registry_entry(self.env_id).options,
                                                       **self.env_options}.get("image_size")
        if obs_mode == "vector":  # every other mode holds images
            return
        if self.multi_agent:
            raise ValueError(f"config: the multi-agent algorithms train on flat-vector observations only; "
                             f"{self.env_id} with obs_mode={obs_mode!r} emits images")
        from sg_torchrl.modules.cnn import DEFAULT_CNN

        smallest = DEFAULT_CNN.min_image_size
        if isinstance(image_size, int) and not isinstance(image_size, bool) and 0 < image_size < smallest:
            raise ValueError(
                f"config: image_size={image_size} is too small for sg-train's CNN encoder (kernels "
                f"{DEFAULT_CNN.kernel_sizes}, strides {DEFAULT_CNN.strides}): use image_size >= {smallest} "
                f"(the Vision ids default to 256, Safety-Gymnasium's size)"
            )

    @property
    def observation_mode(self) -> str:
        """The env's ``obs_mode`` (its registry default, or ``env_options``'): ``"vector"`` or a mode with images."""
        from sg_torchrl.envs.registry import registry_entry

        return {**registry_entry(self.env_id).options, **self.env_options}.get("obs_mode", "vector")

    def _validate_env_kind(self) -> None:
        """``env_id`` is registered (else :class:`~sg_torchrl.envs.UnknownEnvError`, a ``ValueError`` naming
        the closest ids, before anything is built); a multi-agent algorithm needs a multi-agent env id and
        a single-agent one a single-agent id.
        """
        from sg_torchrl.envs import UnknownEnvError, registry_entry

        try:
            env_multi_agent = registry_entry(self.env_id).multi_agent
        except UnknownEnvError as error:
            raise UnknownEnvError(f"config: env_id: {error}") from None
        if env_multi_agent == self.multi_agent:
            return
        if self.multi_agent:
            raise ValueError(
                f"config: algo {self.algo!r} is a multi-agent algorithm but env_id {self.env_id!r} is a single-agent "
                f"env; give a multi-agent env id (e.g. Safety2x3HalfCheetahVelocity-v0, "
                f"sg_torchrl.list_envs(family='multi_agent_velocity')) or a single-agent algo "
                f"({', '.join(ALGORITHM_NAMES)})"
            )
        raise ValueError(
            f"config: algo {self.algo!r} is a single-agent algorithm but env_id {self.env_id!r} is a multi-agent "
            f"env; give a multi-agent algo ({', '.join(MULTI_AGENT_ALGORITHM_NAMES)}) or a single-agent env id "
            f"(e.g. SafetyHalfCheetahVelocity-v1)"
        )

    @property
    def network_sizes(self) -> list[int]:
        """``hidden_sizes``, or when empty the paper's for the algorithm and env (appendix: [128, 128]
        for the multi-agent algorithms; [256, 256] for the Ant and Doggo navigation robots, [64, 64]
        otherwise). With pixel observations these are the MLP layers after the CNN encoder."""
        if self.hidden_sizes:
            return list(self.hidden_sizes)
        if self.multi_agent:
            return [128, 128]
        if self.off_policy:
            return [256, 256]  # OmniSafe's ReLU actor and critics
        from sg_torchrl.envs import registry_entry

        try:
            entry = registry_entry(self.env_id)
        except KeyError:
            return [64, 64]  # an unknown id fails with its own message when the env is built
        large = entry.family in ("navigation", "vision") and entry.robot in ("Ant", "Doggo")
        return [256, 256] if large else [64, 64]

    @property
    def epochs(self) -> int:
        return self.total_steps // self.steps_per_epoch

    @property
    def run_dir(self) -> Path:
        """The run's directory; a seed group's holds the group's config and checkpoint and its seeds' run
        directories (:meth:`seed_dir`)."""
        default = f"seeds-{'-'.join(map(str, self.seeds))}" if self.seeds else f"seed-{self.seed:03d}"
        return Path(self.output_dir) / (self.run_name or f"{self.env_id}/{self.algo}/{default}")

    def seed_dir(self, seed: int) -> Path:
        """Seed ``seed``'s run directory in a seed group: ``<run_dir>/seed-XXX``."""
        return self.run_dir / f"seed-{seed:03d}"

    def for_seed(self, seed: int) -> TrainConfig:
        """The single-seed config of one seed of this group: ``seed`` alone, in its ``seed-XXX`` directory.

        What the group writes to that directory's ``config.json``, so tools that read a run directory
        see the run that seed is.
        """
        return dataclasses.replace(self, seed=seed, seeds=[], output_dir=str(self.run_dir),
                                   run_name=f"seed-{seed:03d}", resume=None, overwrite=False)

    @classmethod
    def from_saved(cls, values: dict[str, Any]) -> TrainConfig:
        """The config saved as ``values`` (``config.json``, a checkpoint's), read past :data:`RETIRED_FIELDS`."""
        return cls(**{name: value for name, value in values.items() if name not in RETIRED_FIELDS})

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def save(self, path: Path) -> None:
        write_atomic(path, json.dumps(self.to_dict(), indent=2), sync=False)



def __getattr__(name: str) -> Any:
    """The command-line helpers, which moved to :mod:`sg_torchrl.train.command_line`, still import from here."""
    if name in _COMMAND_LINE:
        from sg_torchrl.train import command_line

        return getattr(command_line, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


_COMMAND_LINE = ("build_parser", "command_line_values", "parse_args", "parse_env_option")
