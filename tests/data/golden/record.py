"""Record the golden data of ``tests/test_golden_equivalence.py``: each algorithm's small run, as numbers.

**What.** For each of the 16 algorithms one run with seed 0 on the engine ``sg-train --seed 0`` uses
(the fused on-policy family ``OnPolicyGroupTrainer`` for the twelve single-agent algorithms on
``SafetyHalfCheetahVelocity-v1``; for MAPPO, HAPPO, MAPPO-Lag and MACPO on
``Safety2x3HalfCheetahVelocity-v0`` the single-seed ``MultiAgentTrainer`` at the recording commit, now the
multi-agent family with one seed, ``MultiAgentGroupTrainer``), and a seed group ``--seeds 0 1`` of PPO-Lag, CPO and MAPPO-Lag
(``OnPolicyGroupTrainer`` / ``MultiAgentGroupTrainer``). Settings (:func:`run_config`): 2 simulators, 2 epochs of
1,000 steps, 100-step episodes with a 0.5 m/s speed limit (episodes end and cost accrues in epoch 1, so
epoch 2's multiplier update and the learning-rate annealing act), cost limit 20, 2 evaluation episodes.
First order: up to 4 passes of 250-sample minibatches (up to 16 Adam steps an epoch) with a KL early stop at
0.004, which ends epoch 1 after 3 passes for all but FOCOPS; second order: 2 critic passes of 250; multi
agent: the default 5 epochs (MACPO 15 critic epochs) of 2 minibatches of 500.

Not told apart at these settings: NPG and TRPO, RCPO and TRPO-Lag (the line search accepts the full step
in both epochs, so the runs are the same; trust regions up to 2.0 did not make it backtrack). PCPO's does
backtrack (13-16 steps).

Each ``<name>.pt`` (``torch.save``, plain containers and tensors; read with ``weights_only=True``) holds:

* ``"run"``: the ``TrainConfig`` keyword arguments the run was given (the rest are defaults);
* ``"config"``: the resolved config the run wrote to ``config.json`` (but where it wrote);
* ``"seeds"``: per seed, as :func:`test_golden_equivalence.run_case` measures them: ``"progress"``
  (every ``progress.csv`` column but ``Time/*``, a list over its rows: the two epochs, then the row the
  evaluation logs), ``"summary"`` (``summary.json``'s numbers but ``Time/*``) and ``"epochs"``, after
  each epoch (read from the checkpoint written then): ``"episodes"`` (return, cost, length of the
  finished episodes the episode statistics keep) and ``"outputs"`` (the actor's ``loc`` / ``scale`` and
  the critics' values on the probe observations, and the normalisers' ``mean``, ``var``, ``count``);
* ``"commit"``: the commit recorded from (``git rev-parse HEAD``), and ``"dirty"``: whether
  ``sg_torchrl/`` had uncommitted changes then.

``probes.pt`` holds the probe observations per env id: 64 raw observations of each env (every 10th step of
a 640-step rollout of uniformly random actions, env seed 12345, ``torch.manual_seed(12345)``), and for
the multi-agent env the agents' observations ``(64, 2, 12)`` with the global state ``(64, 17)``. It is
written only when absent (the recorded outputs are functions of it).

**Recorded from** commit ``bccbadc`` (the algorithm layer before its rewrite, ``sg_torchrl/`` unchanged),
where two recordings in separate processes were identical bit for bit, probes included.

**Re-running.** From the repository root::

    PYTHONPATH=. .venv/bin/python tests/data/golden/record.py            # every run, into this folder
    PYTHONPATH=. .venv/bin/python tests/data/golden/record.py ppo cpo-seeds-0-1 --out /tmp/golden

About 30 s on 2 cores. Golden data is only worth recording again when the numbers are meant to change
(say so in the commit); recording it from code under test defeats its purpose. ``--check-adapter``
(on by default) checks, with this commit's modules, that ``load_trained``'s rebuilt functions equal the
package's own networks and normalisers on the probes bit for bit (``--no-check-adapter`` once those
modules are gone).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
sys.path.insert(0, str(ROOT / "tests"))

import test_golden_equivalence as golden  # noqa: E402

SINGLE_AGENT_ENV = "SafetyHalfCheetahVelocity-v1"
MULTI_AGENT_ENV = "Safety2x3HalfCheetahVelocity-v0"
ENV_OPTIONS = {"max_episode_steps": 100, "velocity_threshold": 0.5}
SECOND_ORDER = {"npg", "trpo", "trpo_lag", "rcpo", "cpo", "pcpo"}


def run_config(name: str) -> dict[str, Any]:
    """The ``TrainConfig`` keyword arguments of the recorded run ``name`` (``ppo``, ``cpo-seeds-0-1``, ...)."""
    algo, _, seeds = name.partition("-seeds-")
    multi_agent = algo in golden.MULTI_AGENT
    config: dict[str, Any] = dict(
        algo=algo, env_id=MULTI_AGENT_ENV if multi_agent else SINGLE_AGENT_ENV, env_options=dict(ENV_OPTIONS),
        num_envs=2, steps_per_epoch=1000, total_steps=2000, cost_limit=20.0, eval_episodes=2,
    )
    if seeds:
        config["seeds"] = [int(s) for s in seeds.split("-")]
    else:
        config["seed"] = 0
    if multi_agent:
        config["minibatch_size"] = 500
    elif algo in SECOND_ORDER:
        config.update(update_iters=2, minibatch_size=250)
    else:
        config.update(update_iters=4, minibatch_size=250, target_kl=0.004)  # the KL early stop acts in epoch 1
    return config


def make_probes() -> dict[str, dict[str, torch.Tensor]]:
    """64 raw observations per env id from a random-action rollout (see the module docstring)."""
    import sg_torchrl

    probes = {}
    for env_id, keys in ((SINGLE_AGENT_ENV, {"observation": "observation"}),
                         (MULTI_AGENT_ENV, {"agents_observation": ("agents", "observation"), "state": "state"})):
        torch.manual_seed(12345)
        env = sg_torchrl.make(env_id, num_envs=1, seed=12345)
        rollout = env.rollout(640, break_when_any_done=False)
        probes[env_id] = {name: rollout[key][0, ::10].clone().contiguous() for name, key in keys.items()}
        env.close()
    return probes


def check_adapter(run_dir: Path, config: dict[str, Any], probes: dict[str, torch.Tensor]) -> None:
    """``load_trained``'s functions against this commit's own networks and normaliser on ``probes`` (exactly)."""
    from sg_torchrl.envs.normalization import RunningObservationNorm
    from sg_torchrl.train.checkpoint import load_checkpoint

    checkpoint = load_checkpoint(run_dir)
    seed = (config.get("seeds") or [None])[0]
    trained = golden.load_trained(run_dir, seed)
    entry = checkpoint["seeds"][0] if "seeds" in checkpoint else checkpoint
    with torch.no_grad():
        if trained.multi_agent:
            from sg_torchrl.modules import make_multi_agent_networks

            obs, state = probes["agents_observation"], probes["state"]
            nets = make_multi_agent_networks(obs.shape[-1], [3, 3], state.shape[-1])
            nets.load_state_dict(entry["networks"])
            agent_norm = RunningObservationNorm(obs.shape[-2:], in_keys=[("agents", "observation")])
            state_norm = RunningObservationNorm(state.shape[-1:], in_keys=["state"])
            agent_norm.load_state_dict(entry["obs_norms"][0])
            state_norm.load_state_dict(entry["obs_norms"][1])
            obs_n, state_n = agent_norm._apply_transform(obs), state_norm._apply_transform(state)
            assert torch.equal(obs_n, trained.normalise["agents_observation"](obs))
            assert torch.equal(state_n, trained.normalise["state"](state))
            pairs = [(nets.policy(obs_n), trained.actor(obs_n)),
                     (nets.reward_value(state_n), trained.critics["reward"](state_n)),
                     (nets.cost_value(state_n), trained.critics["cost"](state_n))]
        else:
            from sg_torchrl.modules import make_actor_critics
            from torchrl.data import Bounded

            obs = probes["observation"]
            action_dim = entry["networks"]["actor"]["module.0.module.1.state_independent_scale"].shape[0]
            spec = Bounded(-1.0, 1.0, shape=(action_dim,))
            actor, critic, cost_critic = make_actor_critics(obs.shape[-1], spec, [64, 64])
            for module, key in ((actor, "actor"), (critic, "critic"), (cost_critic, "cost_critic")):
                module.load_state_dict(entry["networks"][key])
            norm = RunningObservationNorm(obs.shape[-1:])
            norm.load_state_dict(entry["obs_norm"])
            obs_n = norm._apply_transform(obs)
            assert torch.equal(obs_n, trained.normalise["observation"](obs))
            body = actor.module[0].module  # the (loc, scale) network of the ProbabilisticActor
            pairs = [(body(obs_n), trained.actor(obs_n)),
                     (critic.module(obs_n), trained.critics["reward"](obs_n)),
                     (cost_critic.module(obs_n), trained.critics["cost"](obs_n))]
    for want, got in pairs:
        want, got = (want, got) if isinstance(want, tuple) else ((want,), (got,))
        for a, b in zip(want, got, strict=True):
            assert torch.equal(a, b), f"adapter differs: {(a - b).abs().max()}"


def commit_info() -> tuple[str, bool]:
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
    status = subprocess.run(["git", "status", "--porcelain", "--", "sg_torchrl"], cwd=ROOT, capture_output=True,
                            text=True, check=True)
    return head.stdout.strip(), bool(status.stdout.strip())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help=f"runs to record (default all: {' '.join(golden.CASES)})")
    parser.add_argument("--out", type=Path, default=HERE, help="folder to write <name>.pt and probes.pt into")
    parser.add_argument("--check-adapter", action=argparse.BooleanOptionalAction, default=True)
    args = parser.parse_args(argv)
    names = args.names or list(golden.CASES)
    unknown = sorted(set(names) - set(golden.CASES))
    if unknown:
        parser.error(f"unknown runs {unknown}; choose from {list(golden.CASES)}")
    args.out.mkdir(parents=True, exist_ok=True)
    probes_file = args.out / "probes.pt"
    if not probes_file.exists():
        torch.save(make_probes(), probes_file)
    probes = torch.load(probes_file, weights_only=True)
    commit, dirty = commit_info()
    for name in names:
        start = time.perf_counter()
        config = run_config(name)
        with tempfile.TemporaryDirectory() as root:
            measured = golden.run_case(config, Path(root), probes[config["env_id"]])
            if args.check_adapter:
                check_adapter(Path(root) / "run", config, probes[config["env_id"]])
        data = {"run": config, "config": measured["config"], "seeds": measured["seeds"], "commit": commit,
                "dirty": dirty}
        torch.save(data, args.out / f"{name}.pt")
        print(f"{name}: {time.perf_counter() - start:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
