"""Golden data: what every algorithm's ``sg-train`` run produced on an earlier commit, reproduced by this code.

The algorithm layer is written more than once (the seed-group engine, the multi-agent rounds; a
``LossModule`` trainer until it was retired); before such code is rewritten, the numbers the old code produced are kept as
data, so the new code is compared with them and not with itself. ``tests/data/golden/record.py`` wrote
them (its docstring names the commit and says how to record again); this file runs every recorded
config again on the code as it is now and compares.

**What runs.** One small run per algorithm, seed 0, on the engine ``sg-train --seed 0`` uses (the fused
on-policy family, ``OnPolicyGroupTrainer``, for the twelve single-agent algorithms on
``SafetyHalfCheetahVelocity-v1``; the multi-agent family with one seed, ``MultiAgentGroupTrainer``,
for MAPPO, HAPPO, MAPPO-Lag and MACPO on ``Safety2x3HalfCheetahVelocity-v0``: recorded from the single-seed
multi-agent trainer it replaced), and a seed group ``--seeds 0 1`` of PPO-Lag, CPO and MAPPO-Lag:
2 simulators, 2 epochs of 1,000 steps, 100-step episodes and a 0.5 m/s speed limit (so episodes end and
cost accrues in epoch 1: epoch 2's multiplier update and the actor learning-rate annealing act), a cost
limit of 20, a few minibatch steps per epoch (first order: a KL early stop that acts in epoch 1), 2
deterministic evaluation episodes (``record.py`` says exactly). Each run goes through the public API
(:class:`~sg_torchrl.train.TrainConfig` and the trainer :func:`sg_torchrl.train.train` builds,
:func:`~sg_torchrl.train.trainer_class`, run one epoch per ``run(max_epochs=1)`` call so that its
checkpoint can be read after each epoch; on the recording commit a straight ``train(cfg)`` gave the
same numbers bit for bit) in a temporary directory, wandb disabled. The config of each run is the one stored with its
data (the fields ``record.py`` sets; the rest are ``TrainConfig``'s defaults, so a changed default
shows here too, and the resolved ``config.json`` is compared as well).

**What is compared**, per run and per seed of a group:

* ``progress.csv``: every recorded column (all but ``Time/*``), every row (the two epochs, then the row
  the evaluation logs); the epoch-1 row's ``Metrics/EpRet`` / ``Metrics/EpCost`` fingerprint the
  first epoch's trajectories;
* ``summary.json``: its numbers but ``Time/*`` (last-10-episode figures, the evaluation's);
* after each epoch, from the checkpoint: the finished episodes the episode statistics keep (return,
  cost, length of each: the epoch-1 snapshot is the first epoch's episodes one by one), and the networks
  as functions on the probe observations stored in ``probes.pt``: the actor's Gaussian ``loc`` and
  ``scale`` and each critic's value, the observations normalised as the run normalises them (with the
  normaliser's ``mean`` / ``var`` / ``count`` of then, compared as well); multi agent: per agent, the
  actors on their agent's observation, the centralised critics on the state.

**How closely.** Bit for bit (``torch.equal``; floats with ``==``; NaN equals NaN): on the recording
commit two recordings in separate processes were identical in every quantity, and these tests pass
run all together, in another order, alone, or after other test files, so any difference is a change
in what the code computes. The failure message lists every difference of a run with its size.

A rewrite that only rounds differently (another kernel, another summation order) cannot match bit for
bit, nor closely beyond epoch 1: the simulators are chaotic, and epoch 2 is collected with the epoch-1
update's parameters. Seed 0 of the fused group ``--seeds 0 1`` against the fused ``--seed 0`` run (the
same algorithm; the stacked critics round about 1e-7 apart) shows it: epoch 1's trajectories are
identical and the networks after it agree within 1e-7, while epoch 2's mean return differs by 1.3
(PPO-Lag; CPO 0.8) and the final networks by 0.04-0.23. (MAPPO-Lag's group seed is its single run bit
for bit, as ``tests/test_multi_agent_group.py`` checks.) Setting :data:`EXACT` to ``False`` compares what epoch 1
determines only (:data:`TOLERANT_EPOCHS`: its progress row, the episodes and networks after it) with
``rtol=1e-5, atol=1e-6``, which that pair passes and a 5 % change of PPO's clip ratio fails by far
(``loc`` 3e-3 apart after epoch 1). Turn it knowingly, for a change meant to alter float rounding only.

**Checkpoint format.** :func:`load_trained` is the only code here that knows how a checkpoint is laid out
(where the networks, normalisers and episode statistics are, the networks' parameter names and
activations). When the checkpoint format or the network parameter layout changes, it is the one
thing to update: it must keep returning the same functions of the same parameters.
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import torch

torch.set_num_threads(1)

from sg_torchrl.train import TrainConfig, trainer_class  # noqa: E402
from sg_torchrl.train.checkpoint import load_checkpoint  # noqa: E402
from sg_torchrl.train.config import RETIRED_FIELDS  # noqa: E402

GOLDEN_DIR = Path(__file__).parent / "data" / "golden"
#: The recorded runs: the single-agent algorithms (fused engine, seed 0).
SINGLE_AGENT = ("pg", "ppo", "ppo_lag", "cppo_pid", "focops", "cup", "npg", "trpo", "trpo_lag", "rcpo", "cpo", "pcpo")
#: The multi-agent algorithms (MultiAgentGroupTrainer, seed 0).
MULTI_AGENT = ("mappo", "happo", "mappo_lag", "macpo")
#: Seed groups (``--seeds 0 1``) recorded.
GROUPS = ("ppo_lag", "cpo", "mappo_lag")
GROUP_SEEDS = (0, 1)
#: The data files' names (``<name>.pt``), one per recorded run.
CASES = (*SINGLE_AGENT, *MULTI_AGENT, *(f"{algo}-seeds-{'-'.join(map(str, GROUP_SEEDS))}" for algo in GROUPS))

#: Compare bit for bit (see the module docstring); ``False``: ``allclose`` with :data:`RTOL` / :data:`ATOL`.
EXACT = True
RTOL, ATOL = 1e-5, 1e-6
#: Epochs compared when not :data:`EXACT` (see the module docstring: later ones are not float-stable).
TOLERANT_EPOCHS = 1
#: Recorded runs whose float rounding a deliberate change moved, compared as without :data:`EXACT` (epoch 1)
#: with the tolerance given, and why. MACPO's per-agent trust-region step is now the seed-batched step on
#: one row (one definition of conjugate gradient, Fisher-vector product and line search for every
#: second-order algorithm): its dot products sum in another order than the BLAS ``torch.dot`` of the
#: recorded single-agent step, and ten conjugate-gradient iterations on the Fisher matrix amplify that to
#: 3e-4 relative in the step's statistics (``Misc/FinalStepNorm``) and 2.4e-5 in the policy's mean after
#: epoch 1. The fused engine's runs (every single-agent algorithm, the groups) stay bit for bit.
#: MAPPO, HAPPO and MAPPO-Lag (and the MAPPO-Lag group) train through the seed-batched round, which
#: reproduces the recorded per-agent TorchRL losses and ``torch.optim.Adam`` bit for bit (the reward
#: critic's PopArt batch mean sums each row's contiguous targets, as the recorded ``(samples, 1)`` column
#: did): they are compared exactly. MACPO's critic epochs are that round's too; its step keeps the tolerance above.
ROUNDING_MOVED: dict[str, tuple[float, float]] = {"macpo": (1e-3, 1e-4)}
#: The observation normaliser's epsilon (``RunningObservationNorm``), applied as the runs apply it.
NORM_EPSILON = 1e-8
#: Fields of a recorded config the harness sets itself (where the run writes, nothing it computes).
HARNESS_FIELDS = ("output_dir", "run_name", "wandb", "progress", "overwrite", "resume")


# ---------------------------------------------------------------------- checkpoint adapter
def _layers(state: dict[str, torch.Tensor], prefix: str) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The ``Linear`` layers (weight, bias) of the MLP with state-dict keys ``<prefix><index>.weight``, in order."""
    pattern = re.compile(re.escape(prefix) + r"(\d+)\.weight")
    indices = sorted(int(m[1]) for key in state if (m := pattern.fullmatch(key)))
    if not indices:
        raise KeyError(f"no linear layers under {prefix!r} in {sorted(state)}")
    return [(state[f"{prefix}{i}.weight"], state[f"{prefix}{i}.bias"]) for i in indices]


def _mlp(layers: list[tuple[torch.Tensor, torch.Tensor]], activation: Callable[[torch.Tensor], torch.Tensor]):
    """The MLP function of ``layers``: ``activation`` after every layer but the last."""
    def forward(x: torch.Tensor) -> torch.Tensor:
        for index, (weight, bias) in enumerate(layers):
            x = torch.nn.functional.linear(x, weight, bias)
            if index < len(layers) - 1:
                x = activation(x)
        return x
    return forward


def _normaliser(state: dict[str, torch.Tensor] | None):
    """The normalising function of a ``RunningObservationNorm`` state (identity for ``None``) and its stats."""
    if state is None:
        return (lambda x: x), {}
    mean, var = state["mean"], state["var"]

    def normalise(x: torch.Tensor) -> torch.Tensor:
        return ((x.to(torch.float64) - mean) / torch.sqrt(var + NORM_EPSILON)).to(x.dtype)
    return normalise, {"mean": mean.clone(), "var": var.clone(), "count": state["count"].clone()}


@dataclass
class Trained:
    """A trained run as functions of observations (what :func:`load_trained` returns).

    Single agent: ``normalise["observation"]`` maps raw observations ``(B, D)`` to what the networks
    read; ``actor(obs)`` gives ``(loc, scale)`` ``(B, A)``; ``critics["reward"|"cost"](obs)`` ``(B, 1)``.
    Multi agent: ``normalise["agents_observation"]`` on ``(B, n_agents, D)`` and ``normalise["state"]`` on
    ``(B, S)``; ``actor(agents_obs)`` gives ``(loc, scale)`` ``(B, n_agents, A)`` (padding slots 0 / 1);
    ``critics[...](state)`` ``(B, n_agents, 1)``. ``norm_stats``: each normaliser's ``mean``, ``var``,
    ``count``. ``episodes``: ``(3, E)`` float64 rows return, cost, length of the finished episodes the
    run's episode statistics keep, oldest first.
    """

    multi_agent: bool
    normalise: dict[str, Callable[[torch.Tensor], torch.Tensor]]
    norm_stats: dict[str, dict[str, torch.Tensor]]
    actor: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
    critics: dict[str, Callable[[torch.Tensor], torch.Tensor]]
    episodes: torch.Tensor


def _episodes(stats: dict[str, Any]) -> torch.Tensor:
    """Return, cost and length of the finished episodes kept by an ``EpisodeStats`` state dict."""
    channels = list(stats["channels"])
    recent = stats["recent"]
    return torch.stack([recent[channels.index(name)] for name in ("return", "cost", "length")]).to(torch.float64)


def load_trained(run_dir: str | Path, seed: int | None = None) -> Trained:
    """Rebuild a finished run's actor, critics and normalisers as plain functions, from its checkpoint.

    ``run_dir``: a run's directory, or a seed group's (then ``seed`` picks the seed). The one place that
    knows the checkpoint layout: update it when that layout (or the networks' parameter layout) changes.

    Layout at the recording commit: single agent (fused engine, a single run or a group): the entry of the
    seed under ``checkpoint["seeds"]``, with ``networks`` (``actor``: a tanh MLP under
    ``module.0.module.0.`` and ``module.0.module.1.state_independent_scale``, scale = exp of it;
    ``critic`` / ``cost_critic``: tanh MLPs under ``module.``), ``obs_norm`` and ``stats``. Multi agent:
    ``networks`` (ReLU MLPs ``policy.mlp.agent_networks.<i>.``, ``reward_value.mlp.agent_networks.<i>.``,
    ``cost_value.mlp.agent_networks.<i>.``; scale = sigmoid(``policy.heads.<i>.log_std``) * 0.5),
    ``obs_norms`` (agents' observation, then state) and ``stats``, at the top level of a single run's
    checkpoint and in the seed's entry under ``"seeds"`` of a group's.
    """
    checkpoint = load_checkpoint(run_dir)
    entry = checkpoint
    if "seeds" in checkpoint:
        entries = checkpoint["seeds"]
        if seed is None:
            if len(entries) != 1:
                raise ValueError(f"{run_dir} is a seed group's run: give the seed")
            entry = entries[0]
        else:
            entry = next(e for e in entries if e["seed"] == seed)
    networks = entry["networks"]
    if "actor" in networks:  # single agent
        normalise, stats = _normaliser(entry["obs_norm"])
        actor_state = networks["actor"]
        mean_net = _mlp(_layers(actor_state, "module.0.module.0."), torch.tanh)
        log_scale = actor_state["module.0.module.1.state_independent_scale"]

        def actor(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            loc = mean_net(obs)
            return loc, torch.exp(log_scale).expand_as(loc)

        critics = {name: _mlp(_layers(networks[key], "module."), torch.tanh)
                   for name, key in (("reward", "critic"), ("cost", "cost_critic"))}
        return Trained(False, {"observation": normalise}, {"observation": stats} if stats else {}, actor, critics,
                       _episodes(entry["stats"]))

    norms = entry["obs_norms"] or [None, None]
    (obs_normalise, obs_stats), (state_normalise, state_stats) = (_normaliser(s) for s in norms)
    agents = sorted({int(m[1]) for key in networks if (m := re.match(r"policy\.heads\.(\d+)\.log_std$", key))})
    log_stds = [networks[f"policy.heads.{i}.log_std"] for i in agents]
    padded = max(len(s) for s in log_stds)
    means = [_mlp(_layers(networks, f"policy.mlp.agent_networks.{i}."), torch.relu) for i in agents]

    def ma_actor(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        locs, scales = [], []
        for i, (net, log_std) in enumerate(zip(means, log_stds)):
            loc = net(obs[..., i, :])
            loc = torch.cat([loc[..., :len(log_std)], torch.zeros_like(loc[..., len(log_std):])], -1)
            scale = torch.nn.functional.pad(torch.sigmoid(log_std) * 0.5, (0, padded - len(log_std)), value=1.0)
            locs.append(loc)
            scales.append(scale.expand_as(loc))
        return torch.stack(locs, -2), torch.stack(scales, -2)

    def ma_critic(name: str):
        nets = [_mlp(_layers(networks, f"{name}.mlp.agent_networks.{i}."), torch.relu) for i in agents]
        return lambda state: torch.stack([net(state) for net in nets], -2)

    stats = {key: value for key, value in (("agents_observation", obs_stats), ("state", state_stats)) if value}
    return Trained(True, {"agents_observation": obs_normalise, "state": state_normalise}, stats, ma_actor,
                   {"reward": ma_critic("reward_value"), "cost": ma_critic("cost_value")}, _episodes(entry["stats"]))


# ---------------------------------------------------------------------- one run's measurements
def functional_outputs(trained: Trained, probes: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The trained networks on ``probes`` (raw observations, normalised here as the run normalises them)."""
    with torch.no_grad():
        if trained.multi_agent:
            obs = trained.normalise["agents_observation"](probes["agents_observation"])
            state = trained.normalise["state"](probes["state"])
            critic_input = state
        else:
            obs = trained.normalise["observation"](probes["observation"])
            critic_input = obs
        loc, scale = trained.actor(obs)
        out = {"loc": loc, "scale": scale,
               **{f"{name}_value": critic(critic_input) for name, critic in trained.critics.items()}}
    for key, stats in trained.norm_stats.items():
        out.update({f"{key}_norm_{name}": value for name, value in stats.items()})
    return out


def read_progress(path: Path) -> dict[str, list[float]]:
    """Every column of ``progress.csv`` but ``Time/*``, as floats per epoch."""
    with path.open() as handle:
        rows = list(csv.DictReader(handle))
    columns = [name for name in rows[0] if not name.startswith("Time/")] if rows else []
    return {name: [float(row[name]) if row[name] != "" else math.nan for row in rows] for name in columns}


def read_summary(path: Path) -> dict[str, float]:
    """The numbers of ``summary.json`` but ``Time/*``."""
    summary = json.loads(path.read_text())
    return {k: float(v) for k, v in summary.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and not k.startswith("Time/")}


def run_case(config: dict[str, Any], root: Path, probes: dict[str, torch.Tensor]) -> dict[str, Any]:
    """Train ``config`` (``TrainConfig`` keyword arguments) under ``root``; each seed's measurements.

    The run is ``sg_torchrl.train.train``'s (the trainer of :func:`~sg_torchrl.train.trainer_class`, new run),
    driven one epoch per ``run(max_epochs=1)`` call so that its checkpoint can be read after every epoch
    (the trainer checkpoints the first epoch of each call; a straight ``run()`` gives the same numbers).
    Returns ``{"config": the resolved config (config.json but the harness fields), "seeds": {seed:
    {"progress", "summary", "epochs": [after each epoch: {"episodes", "outputs"}]}}}``.
    """
    cfg = TrainConfig(**config, output_dir=str(root), run_name="run", wandb="disabled", progress=False)
    trainer = trainer_class(cfg)(cfg, None)
    run_dir = Path(cfg.run_dir)
    seeds = list(cfg.seeds) if cfg.seeds else [cfg.seed]
    snapshots: dict[int, list[dict[str, Any]]] = {seed: [] for seed in seeds}
    for _ in range(cfg.epochs):
        trainer.run(max_epochs=1)
        for seed in seeds:
            trained = load_trained(run_dir, seed if cfg.seeds else None)
            snapshots[seed].append({"episodes": trained.episodes, "outputs": functional_outputs(trained, probes)})
    resolved = {k: v for k, v in json.loads((run_dir / "config.json").read_text()).items()
                if k not in HARNESS_FIELDS}
    measured = {}
    for seed in seeds:
        seed_dir = run_dir / f"seed-{seed:03d}" if cfg.seeds else run_dir
        measured[seed] = {"progress": read_progress(seed_dir / "progress.csv"),
                          "summary": read_summary(seed_dir / "summary.json"), "epochs": snapshots[seed]}
    return {"config": resolved, "seeds": measured}


def load_golden(name: str) -> dict[str, Any]:
    return torch.load(GOLDEN_DIR / f"{name}.pt", weights_only=True)


def load_probes(env_id: str) -> dict[str, torch.Tensor]:
    return torch.load(GOLDEN_DIR / "probes.pt", weights_only=True)[env_id]


# ---------------------------------------------------------------------- comparison
def _float_equal(a: float, b: float, exact: bool, rtol: float, atol: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return a == b if exact else math.isclose(a, b, rel_tol=rtol, abs_tol=atol)


def _tensor_mismatch(got: torch.Tensor, want: torch.Tensor, exact: bool, rtol: float, atol: float) -> str | None:
    if got.shape != want.shape or got.dtype != want.dtype:
        return f"shape/dtype {tuple(got.shape)} {got.dtype}, recorded {tuple(want.shape)} {want.dtype}"
    same = torch.equal(got, want) if exact else torch.allclose(got, want, rtol=rtol, atol=atol, equal_nan=True)
    if same:
        return None
    diff = (got.double() - want.double()).abs()
    rel = diff / want.double().abs().clamp_min(1e-12)
    return (f"max |diff| {diff.max().item():.3g}, max rel {rel.max().item():.3g} "
            f"({int((diff > 0).sum())} of {diff.numel()} differ)")


def mismatches(got: dict[str, Any], want: dict[str, Any], tolerance: tuple[float, float] | None = None) -> list[str]:
    """Every difference between a run's measurements and the recorded ones (empty: they agree).

    With :data:`EXACT` and no ``tolerance`` everything is compared bit for bit; else only what the first
    :data:`TOLERANT_EPOCHS` epochs determine (their progress rows, the networks and episodes after them),
    with ``(rtol, atol)`` (:data:`RTOL` / :data:`ATOL` by default), and the summary (end of run) is not
    compared.
    """
    exact = EXACT and tolerance is None
    rtol, atol = tolerance or (RTOL, ATOL)
    epochs = None if exact else TOLERANT_EPOCHS
    problems = []
    for key, value in want["config"].items():
        if key in RETIRED_FIELDS:  # recorded by a version that still had it (engine: the one that is left)
            continue
        if got["config"].get(key, "<missing>") != value:
            problems.append(f"config {key}: {got['config'].get(key, '<missing>')!r}, recorded {value!r}")
    for seed, recorded in want["seeds"].items():
        measured = got["seeds"][seed]
        parts = [("progress", column, values[:epochs], measured["progress"].get(column))
                 for column, values in recorded["progress"].items()]
        if exact:
            parts += [("summary", key, [value], None if key not in measured["summary"] else [measured["summary"][key]])
                      for key, value in recorded["summary"].items()]
        for part, column, old, new in parts:
            if new is None:
                problems.append(f"seed {seed} {part}: {column} missing")
                continue
            new = new[:epochs]
            if len(new) != len(old):
                problems.append(f"seed {seed} {part} {column}: {len(new)} rows, recorded {len(old)}")
                continue
            bad = [(i, a, b) for i, (a, b) in enumerate(zip(new, old)) if not _float_equal(a, b, exact, rtol, atol)]
            if bad:
                i, a, b = bad[0]
                problems.append(f"seed {seed} {part} {column}: {len(bad)} value(s) differ, first (row {i}) {a!r}, "
                                f"recorded {b!r}")
        if len(measured["epochs"]) != len(recorded["epochs"]):
            problems.append(f"seed {seed}: {len(measured['epochs'])} epochs, recorded {len(recorded['epochs'])}")
        for epoch, (new, old) in enumerate(list(zip(measured["epochs"], recorded["epochs"]))[:epochs], start=1):
            for name, tensor in (("episodes", old["episodes"]), *old["outputs"].items()):
                value = new["episodes"] if name == "episodes" else new["outputs"].get(name)
                if value is None:
                    problems.append(f"seed {seed} after epoch {epoch} {name}: missing")
                elif (problem := _tensor_mismatch(value, tensor, exact, rtol, atol)) is not None:
                    problems.append(f"seed {seed} after epoch {epoch} {name}: {problem}")
    return problems


# ---------------------------------------------------------------------- tests
@pytest.mark.parametrize("name", CASES)
def test_golden_run(name: str, tmp_path: Path) -> None:
    """The run recorded as ``name`` trains to the recorded numbers (see the module docstring)."""
    golden = load_golden(name)
    got = run_case(golden["run"], tmp_path, load_probes(golden["config"]["env_id"]))
    problems = mismatches(got, golden, ROUNDING_MOVED.get(name))
    assert not problems, (f"{name}: {len(problems)} difference(s) from the golden data recorded at "
                          f"{golden['commit'][:12]}:\n  " + "\n  ".join(problems))


def test_golden_files_cover_every_algorithm() -> None:
    """Every algorithm has its recorded run, with the settings the module docstring describes."""
    assert {name.split("-")[0] for name in CASES} == set(SINGLE_AGENT) | set(MULTI_AGENT)
    for name in CASES:
        golden = load_golden(name)
        config = golden["config"]
        assert config["algo"] == name.split("-")[0]
        assert config["total_steps"] == 2 * config["steps_per_epoch"]
        assert config["engine"] == (None if config["algo"] in MULTI_AGENT else "fused")  # the engine that is left
        assert list(golden["seeds"]) == (list(GROUP_SEEDS) if "-seeds-" in name else [0])
