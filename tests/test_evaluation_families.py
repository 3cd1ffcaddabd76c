"""``sg-eval``, ``load_policy`` and export for the off-policy and multi-agent families.

Each family trains a tiny run here (a few hundred steps, 16-unit networks, 50-step episodes), then:
``sg-eval`` without options reproduces the evaluation figures of the run's ``summary.json`` exactly; the
loaded policy's actions equal those of the engine's evaluation actor (its module rebuilt from the
checkpoint as the engine builds it, its frozen normaliser in front); the exported program, run in a clean
interpreter without sg_torchrl, gives the same actions. The single-agent on-policy family is
``tests/test_evaluation.py``'s.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

import sg_torchrl
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.evaluation import cli
from sg_torchrl.evaluation.networks import OffPolicyActorNetwork
from sg_torchrl.evaluation.policy import load_policy
from sg_torchrl.modules.off_policy import StackedOffPolicyNets, make_off_policy_networks
from sg_torchrl.train import TrainConfig, train
from sg_torchrl.train.checkpoint import load_checkpoint
from sg_torchrl.train.multi_agent import make_team_networks
from sg_torchrl.train.off_policy import off_policy_network_options
from sg_torchrl.train.seed_runs import seed_entry

from export_checks import run_exported

torch.set_num_threads(1)
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

EVAL_METRICS = ("Metrics/EvalEpRet", "Metrics/EvalEpRetStd", "Metrics/EvalEpCost", "Metrics/EvalEpCostStd",
                "Metrics/EvalEpLen")
VELOCITY = "SafetyHalfCheetahVelocity-v1"
TEAM = "Safety2x3HalfCheetahVelocity-v0"
#: Run name -> (algo, env id, seeds or a single seed): SAC as a seed group, TD3 and DDPG-Lag single runs, a
#: team of two agents as a group and six heterogeneous agents (padded observations and actions) alone.
RUNS = {
    "sac": ("sac", VELOCITY, [0, 1]), "td3": ("td3", VELOCITY, 2), "ddpg_lag": ("ddpg_lag", VELOCITY, 0),
    "mappo_lag": ("mappo_lag", TEAM, [0, 1]), "happo": ("happo", "Safety6x1HalfCheetahVelocity-v0", 1),
}
OFF_POLICY = ("sac", "td3", "ddpg_lag")
MULTI_AGENT = ("mappo_lag", "happo")


def _config(name: str, output: Path) -> TrainConfig:
    algo, env_id, seeds = RUNS[name]
    family = dict(warmup_steps=100, minibatch_size=16, replay_size=1000) if algo in OFF_POLICY else dict(update_iters=2)
    where = dict(seeds=seeds) if isinstance(seeds, list) else dict(seed=seeds)
    return TrainConfig(algo=algo, env_id=env_id, env_options={"max_episode_steps": 50}, num_envs=2,
                       steps_per_epoch=200, total_steps=200, hidden_sizes=[16, 16], eval_episodes=2, wandb="disabled",
                       progress=False, output_dir=str(output), run_name=name, **where, **family)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Every run of RUNS, trained once (about a second each)."""
    output = tmp_path_factory.mktemp("runs")
    trained = {}
    for name in RUNS:
        cfg = _config(name, output)
        train(cfg)
        trained[name] = cfg.run_dir
    return trained


def _seeds(name: str) -> list[int]:
    seeds = RUNS[name][2]
    return seeds if isinstance(seeds, list) else [seeds]


def _own_summary(run_dir: Path, name: str, seed: int) -> dict:
    group = isinstance(RUNS[name][2], list)
    return json.loads((run_dir / (f"seed-{seed:03d}" if group else ".") / "summary.json").read_text())


# ---------------------------------------------------------------------------- sg-eval reproduces training
@pytest.mark.parametrize("name", list(RUNS))
def test_sg_eval_reproduces_the_runs_evaluation(runs, name, tmp_path):
    assert cli.main([str(runs[name]), "--output-dir", str(tmp_path)]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert [int(seed) for seed in summary["seeds"]] == _seeds(name)
    for seed in _seeds(name):
        own = _own_summary(runs[name], name, seed)
        for metric in EVAL_METRICS:  # exactly, not approximately
            assert summary["seeds"][str(seed)][metric] == own[metric], (name, seed, metric)


# ---------------------------------------------------------------------------- off-policy actors
def _engine_actor(run_dir: Path, seed: int) -> tuple[torch.nn.Module, tuple]:
    """The seed's actor as the engine evaluates it (make_off_policy_networks' module, the entry's weights), and
    its networks for the stacked engine."""
    entry = seed_entry(load_checkpoint(run_dir), seed)
    cfg = TrainConfig.from_saved(entry["config"])
    env = sg_torchrl.make(cfg.env_id, num_envs=1, **cfg.env_options)
    actor, critics, costs = make_off_policy_networks(17, env.action_spec[0], cfg.network_sizes,
                                                     **off_policy_network_options(cfg.algo))
    actor.load_state_dict(entry["networks"]["actor"])
    for module, state in zip([*critics, *costs], [*entry["networks"]["critics"], *entry["networks"]["cost_critics"]]):
        module.load_state_dict(state)
    return actor, (actor, critics, costs, env.action_spec[0], cfg)


@pytest.mark.parametrize("name", OFF_POLICY)
def test_off_policy_policy_acts_as_the_engines_actor(runs, name):
    seed = _seeds(name)[-1]
    policy = load_policy(runs[name], seed=seed)
    actor, (_, critics, costs, spec, cfg) = _engine_actor(runs[name], seed)
    obs = torch.randn(500, 17, generator=torch.Generator().manual_seed(0)) * 3
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = actor(TensorDict({"observation": obs.clone()}, batch_size=[500]))["action"]
    assert torch.equal(torch.from_numpy(policy.act(obs.numpy())), expected)
    assert torch.equal(policy(TensorDict({"observation": obs.clone()}, batch_size=[500]))["action"], expected)
    # The stacked engine's deterministic action (collection, the actor's steps): the same bits.
    stacked = StackedOffPolicyNets.from_single([(actor, critics, costs)], 17, spec, cfg.network_sizes,
                                               stochastic=policy.stochastic)
    assert torch.equal(stacked.action(stacked.actor, obs[None])[0].detach(), expected)
    assert policy.stochastic is (name == "sac") and policy.seed == seed and policy.epoch == 1
    td = TensorDict({"observation": obs.clone()}, batch_size=[500])
    with set_exploration_type(ExplorationType.RANDOM):
        sampled = policy(td)["action"]
    assert torch.equal(sampled, expected) is (name != "sac")  # TD3 and DDPG act deterministically
    assert (sampled.abs() <= 1).all()
    if name == "sac":
        assert not np.array_equal(policy.act(obs[0].numpy(), deterministic=False), policy.act(obs[0].numpy()))
    else:
        with pytest.raises(ValueError, match="deterministic"):
            policy.act(obs.numpy(), deterministic=False)


@pytest.mark.parametrize("stochastic", [True, False])
def test_off_policy_network_keeps_the_actors_bits_for_any_bounds(stochastic):
    """Bounds other than [-1, 1] rescale the squashed action as the TorchRL actor does, bit for bit."""
    spec = Bounded(low=torch.tensor([-0.4, -2.0, 0.0]), high=torch.tensor([0.4, 1.0, 3.0]), shape=(3,))
    actor = make_off_policy_networks(5, spec, [8], stochastic=stochastic, num_critics=1, constrained=False)[0]
    network = OffPolicyActorNetwork.from_actor(actor, stochastic=stochastic)
    obs = torch.randn(200, 5, generator=torch.Generator().manual_seed(1)) * 4
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = actor(TensorDict({"observation": obs}, batch_size=[200]))["action"]
        assert torch.equal(network.mean_action(obs), expected)
    assert ((expected >= spec.space.low) & (expected <= spec.space.high)).all()


def test_stochastic_evaluation_of_a_deterministic_actor_is_refused(runs, tmp_path, capsys):
    assert cli.main([str(runs["td3"]), "--stochastic", "--output-dir", str(tmp_path / "td3")]) == 2
    assert "td3 actor is deterministic" in capsys.readouterr().err
    assert not (tmp_path / "td3").exists()
    assert cli.main([str(runs["sac"]), "--seeds", "0", "--stochastic", "--output-dir", str(tmp_path / "sac")]) == 0
    summary = json.loads((tmp_path / "sac" / "summary.json").read_text())
    assert summary["deterministic"] is False
    assert summary["seeds"]["0"]["Metrics/EvalEpRet"] != _own_summary(runs["sac"], "sac", 0)["Metrics/EvalEpRet"]


# ---------------------------------------------------------------------------- teams
def _engine_team(run_dir: Path, seed: int) -> tuple[torch.nn.Module, RunningObservationNorm, torch.Size]:
    """The seed's team as the engine evaluates it: its actor (make_team_networks') and frozen normalisers."""
    entry = seed_entry(load_checkpoint(run_dir), seed)
    cfg = TrainConfig.from_saved(entry["config"])
    env = sg_torchrl.make(cfg.env_id, num_envs=1, **cfg.env_options)
    networks = make_team_networks(env, cfg)
    networks.load_state_dict(entry["networks"])
    shape = env.observation_spec["agents", "observation"].shape[1:]
    norm = RunningObservationNorm(shape, in_keys=[("agents", "observation")])
    norm.load_state_dict(entry["obs_norms"][0])
    return networks.actor, norm.freeze(), shape


@pytest.mark.parametrize("name", MULTI_AGENT)
def test_team_policy_acts_as_the_engines_team(runs, name):
    seed = _seeds(name)[-1]
    policy = load_policy(runs[name], seed=seed)
    actor, norm, shape = _engine_team(runs[name], seed)
    obs = torch.randn(300, *shape, generator=torch.Generator().manual_seed(2)) * 3
    td = TensorDict({"agents": TensorDict({"observation": obs.clone()}, batch_size=[300, shape[0]])}, batch_size=[300])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = actor(norm(td.clone()))["agents", "action"]
    assert policy.in_keys == [("agents", "observation")] and policy.out_keys == [("agents", "action")]
    assert policy.network.scaler is not None and policy.seed == seed
    assert torch.equal(torch.from_numpy(policy.act(obs.numpy())), expected)
    assert torch.equal(policy(td)["agents", "action"], expected)
    assert torch.equal(td["agents", "observation"], obs)  # the raw observation is left as it was
    single = policy.act(obs[0].numpy())
    assert single.shape == policy.action_shape == tuple(expected.shape[1:]) and single.dtype == np.float32
    np.testing.assert_allclose(single, expected[0].numpy(), rtol=1e-6, atol=1e-6)  # a batch of 1: other rounding
    with pytest.raises(ValueError, match="shape"):
        policy.act(np.zeros((shape[0] + 1, shape[1])))
    sizes = sg_torchrl.make(policy.config.env_id, num_envs=1).action_sizes
    for agent, size in enumerate(sizes):  # an agent's padding slots stay zero
        assert (expected[:, agent, size:] == 0).all()


def test_team_policy_is_a_torchrl_policy(runs):
    policy = load_policy(runs["mappo_lag"], seed=0)
    env = sg_torchrl.make(TEAM, num_envs=3, seed=4, max_episode_steps=50)
    rollout = env.rollout(5, policy)
    assert rollout["agents", "action"].shape == (3, 5, 2, 3)
    td = env.reset()
    with set_exploration_type(ExplorationType.RANDOM):
        sampled = policy(td.clone())["agents", "action"]
    assert not torch.equal(sampled, policy(td.clone())["agents", "action"])


def test_a_team_is_not_evaluated_on_another_partition(runs, tmp_path, capsys):
    code = cli.main([str(runs["mappo_lag"]), "--seeds", "0", "--env-id", "Safety6x1HalfCheetahVelocity-v0",
                     "--output-dir", str(tmp_path)])
    assert code == 2 and "the policy was trained on {('agents', 'observation'): (2, 12)}" in capsys.readouterr().err
    assert not tmp_path.joinpath("summary.json").exists()


# ---------------------------------------------------------------------------- export
def test_every_familys_export_runs_without_sg_torchrl(runs, tmp_path):
    programs, expected = [], []
    for name in (*OFF_POLICY, *MULTI_AGENT):
        seed = _seeds(name)[0]
        target = tmp_path / f"{name}.pt2"
        assert cli.main([str(runs[name]), "--seeds", str(seed), "--episodes", "0", "--export", str(target)]) == 0
        policy = load_policy(runs[name], seed=seed)
        shape = next(iter(policy.input_shapes.values()))
        obs = torch.randn(64, *shape, generator=torch.Generator().manual_seed(3)) * 3
        programs.append((target, obs))
        expected.append(torch.from_numpy(policy.act(obs.numpy())))
        description = {"sg_torchrl.json": ""}
        torch.export.load(target, extra_files=description)
        assert json.loads(description["sg_torchrl.json"])["action_shape"] == list(policy.action_shape)
    for name, exported, wanted in zip((*OFF_POLICY, *MULTI_AGENT), run_exported(programs, tmp_path), expected):
        assert exported.shape == wanted.shape, name
        torch.testing.assert_close(exported, wanted, rtol=0, atol=1e-6, msg=name)
