"""``sg-eval`` and ``sg_torchrl.load_policy`` (:mod:`sg_torchrl.evaluation`): loading, evaluating, watching, exporting.

``tests/data/eval_run`` is a committed seed group kept with its checkpoint, made with::

    sg-train --algo ppo_lag --env-id SafetyPointGoal1-v0 --seeds 0 1 --total-steps 4000 --steps-per-epoch 2000 \\
        --num-envs 2 --eval-episodes 4 --wandb disabled --output-dir runs --run-name ppo_lag-pointgoal1

(its csv/ and curves.png left out). ``sg-eval`` without options must reproduce the evaluation figures of
its ``summary.json`` files exactly. Video tests need an OpenGL backend (the ``backend`` fixture skips
without one), and so does the pixel run (its observations are rendered).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

import sg_torchrl
from sg_torchrl.envs.normalization import RunningObservationNorm
from sg_torchrl.evaluation import cli
from sg_torchrl.evaluation.policy import PolicyLoadError, load_policy
from sg_torchrl.modules.mlp import make_actor
from sg_torchrl.train import TrainConfig, train
from sg_torchrl.train.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from sg_torchrl.train.seed_runs import seed_entry

from export_checks import run_exported

torch.set_num_threads(1)

DATA = Path(__file__).parent / "data"
EVAL_METRICS = ("Metrics/EvalEpRet", "Metrics/EvalEpRetStd", "Metrics/EvalEpCost", "Metrics/EvalEpCostStd",
                "Metrics/EvalEpLen")


@pytest.fixture
def group_run(tmp_path: Path) -> Path:
    """A copy of the committed seed group (sg-eval writes into the run's eval/)."""
    return Path(shutil.copytree(DATA / "eval_run", tmp_path / "run"))


@pytest.fixture(scope="module")
def single_run(tmp_path_factory) -> Path:
    """A single-seed run (the single-seed layout: no seed-XXX/), trained for two short epochs."""
    cfg = TrainConfig(algo="ppo_lag", env_id="SafetyPointGoal1-v0", seed=3, total_steps=400, steps_per_epoch=200,
                      num_envs=2, update_iters=2, eval_episodes=2, wandb="disabled", progress=False,
                      output_dir=str(tmp_path_factory.mktemp("single")), run_name="run")
    train(cfg)
    return cfg.run_dir


def run_eval(*argv: str, capsys=None) -> tuple[int, str, str]:
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr() if capsys is not None else ("", "")
    return code, out, err


# ---------------------------------------------------------------------------- reproducing training's evaluation
def test_sg_eval_reproduces_the_committed_group_evaluation(group_run, capsys):
    code, out, _ = run_eval(group_run, capsys=capsys)
    assert code == 0
    summary = json.loads((group_run / "eval" / "summary.json").read_text())
    trained = json.loads((group_run / "summary.json").read_text())
    for seed in ("0", "1"):
        own = json.loads((group_run / f"seed-00{seed}" / "summary.json").read_text())
        for name in EVAL_METRICS:  # exactly, not approximately
            assert summary["seeds"][seed][name] == own[name] == trained["seeds"][seed][name], (seed, name)
    for name in EVAL_METRICS:
        assert summary["mean"][name] == trained["mean"][name], name
    assert summary["episodes"] == 4 and summary["deterministic"] is True
    assert [summary["seeds"][s]["env_seed"] for s in ("0", "1")] == [10_000, 10_001]
    rows = (group_run / "eval" / "episodes.csv").read_text().splitlines()
    assert rows[0] == "seed,episode,env_seed,return,cost,length" and len(rows) == 1 + 2 * 4
    costs = [float(row.split(",")[4]) for row in rows[1:5]]
    assert np.mean(costs) == summary["seeds"]["0"]["Metrics/EvalEpCost"]
    assert "mean" in out and "PPO-Lag on SafetyPointGoal1-v0" in out


def test_sg_eval_reproduces_a_single_run(single_run, tmp_path):
    assert cli.main([str(single_run), "--output-dir", str(tmp_path / "eval")]) == 0
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    own = json.loads((single_run / "summary.json").read_text())
    assert list(summary["seeds"]) == ["3"]
    for name in EVAL_METRICS:
        assert summary["seeds"]["3"][name] == own[name], name


def test_a_seed_directory_of_a_group_evaluates_that_seed(group_run, tmp_path):
    assert cli.main([str(group_run / "seed-001"), "--output-dir", str(tmp_path / "one")]) == 0
    assert list(json.loads((tmp_path / "one" / "summary.json").read_text())["seeds"]) == ["1"]
    assert cli.main([str(group_run), "--seeds", "1", "--output-dir", str(tmp_path / "two")]) == 0
    assert (tmp_path / "one" / "summary.json").read_text() == (tmp_path / "two" / "summary.json").read_text()


def test_options_seed_and_stochastic_change_the_evaluation(group_run, tmp_path):
    base = [str(group_run), "--seeds", "0", "--episodes", "2"]

    def figures(name: str, *extra: str) -> dict:
        assert cli.main([*base, "--output-dir", str(tmp_path / name), *extra]) == 0
        return json.loads((tmp_path / name / "summary.json").read_text())

    plain, other_seed = figures("plain"), figures("seed", "--seed", "77")
    assert other_seed["seeds"]["0"]["env_seed"] == 77
    assert other_seed["seeds"]["0"]["Metrics/EvalEpRet"] != plain["seeds"]["0"]["Metrics/EvalEpRet"]
    stochastic, again = figures("stoch", "--stochastic"), figures("stoch2", "--stochastic")
    assert stochastic["deterministic"] is False
    assert stochastic["seeds"] == again["seeds"]  # the action noise is seeded from the env seed
    assert stochastic["seeds"]["0"]["Metrics/EvalEpRet"] != plain["seeds"]["0"]["Metrics/EvalEpRet"]
    short = figures("options", "--env-options", "max_episode_steps=100")
    assert short["env_options"] == {"max_episode_steps": 100}
    assert short["seeds"]["0"]["Metrics/EvalEpLen"] == 100


# ---------------------------------------------------------------------------- load_policy
def test_load_policy_acts_as_the_trainers_actor_and_normaliser(group_run):
    """The folded normaliser is RunningObservationNorm's frozen transform bit for bit, the actor the checkpoint's."""
    policy = load_policy(group_run, seed=1)
    entry = seed_entry(load_checkpoint(group_run), 1)
    env = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=1)
    actor = make_actor(env.observation_spec, env.action_spec, [64, 64])
    actor.load_state_dict(entry["networks"]["actor"])
    norm = RunningObservationNorm((60,))
    norm.load_state_dict(entry["obs_norm"])
    norm.freeze()
    obs = torch.randn(1000, 60, generator=torch.Generator().manual_seed(0)) * 3
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = actor(norm(TensorDict({"observation": obs.clone()}, batch_size=[1000])))["loc"]
    assert torch.equal(torch.from_numpy(policy.act(obs.numpy())), expected)
    td = TensorDict({"observation": obs.clone()}, batch_size=[1000])
    assert torch.equal(policy(td)["action"], expected)  # default: the mean action
    assert torch.equal(td["observation"], obs)  # the raw observation is left as it was
    assert policy.seed == 1 and policy.epoch == 2 and policy.config.env_id == "SafetyPointGoal1-v0"


def test_policy_is_a_torchrl_policy_respecting_the_exploration_type(group_run):
    policy = load_policy(group_run, seed=0)
    env = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=3, seed=5)
    rollout = env.rollout(5, policy)
    assert rollout["action"].shape == (3, 5, 2)
    td = env.reset()
    mean = policy(td.clone())["action"]
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(policy(td.clone())["action"], mean)
    with set_exploration_type(ExplorationType.RANDOM):
        first, second = policy(td.clone())["action"], policy(td.clone())["action"]
    assert not torch.equal(first, mean) and not torch.equal(first, second)
    single = policy.act(td["observation"][0].numpy())
    assert single.shape == (2,) and single.dtype == np.float32
    np.testing.assert_allclose(single, mean[0].numpy(), rtol=0, atol=1e-6)  # a batch of 1: other matmul rounding
    assert np.array_equal(policy.act(td["observation"].numpy()), mean.numpy())
    with pytest.raises(ValueError, match="shape"):
        policy.act(np.zeros(59))
    assert not np.array_equal(policy.act(td["observation"][0].numpy(), deterministic=False), single)


def test_load_policy_of_a_single_run_needs_no_seed(single_run):
    assert load_policy(single_run).seed == 3
    assert sg_torchrl.load_policy(single_run, seed=3).seed == 3
    with pytest.raises(PolicyLoadError, match=r"seed 4 is not in the run .* it holds seed 3"):
        load_policy(single_run, seed=4)


def test_load_policy_refusals(group_run, tmp_path):
    with pytest.raises(PolicyLoadError, match=r"seed group \(seeds 0, 1\): give the seed"):
        load_policy(group_run)
    with pytest.raises(PolicyLoadError, match=r"seed 7 is not in the run .* seeds 0, 1"):
        load_policy(group_run, seed=7)
    with pytest.raises(FileNotFoundError, match="no checkpoint in"):
        load_policy(tmp_path)  # a directory that holds no run
    with pytest.raises(FileNotFoundError, match="no run at"):
        load_policy(tmp_path / "missing")
    data = bytearray((group_run / "checkpoint.pt").read_bytes())
    data[-100] ^= 0xFF
    (group_run / "checkpoint.pt").write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="corrupted"):
        load_policy(group_run, seed=0)


def test_a_checkpoint_of_the_replaced_multi_agent_trainer_loads_as_its_one_seed():
    """Its team's entries at the top level (tests/data/multi_agent_trainer_run): read as the one-seed group's."""
    policy = load_policy(DATA / "multi_agent_trainer_run")
    state = load_checkpoint(DATA / "multi_agent_trainer_run")
    assert policy.seed == state["config"]["seed"] and policy.epoch == state["epoch"]
    assert policy.in_keys == [("agents", "observation")] and policy.out_keys == [("agents", "action")]
    weight = next(v for k, v in state["networks"].items() if k.startswith("policy.") and k.endswith("weight"))
    assert any(torch.equal(weight, p) for p in policy.network.head.parameters())


def test_a_checkpoint_whose_actor_does_not_fit_its_config_is_refused(group_run, tmp_path):
    state = load_checkpoint(group_run)
    state["config"]["hidden_sizes"] = [32]
    save_checkpoint(state, tmp_path / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="does not fit"):
        load_policy(tmp_path, seed=0)


# ---------------------------------------------------------------------------- export
def test_export_runs_without_sg_torchrl(group_run, tmp_path):
    target = tmp_path / "policy.pt2"
    assert cli.main([str(group_run), "--seeds", "1", "--episodes", "0", "--export", str(target)]) == 0
    assert not (group_run / "eval").exists()  # --episodes 0: nothing evaluated, nothing written there
    obs = torch.randn(1000, 60, generator=torch.Generator().manual_seed(1)) * 3
    [exported] = run_exported([(target, obs)], tmp_path)
    expected = torch.from_numpy(load_policy(group_run, seed=1).act(obs.numpy()))
    assert exported.shape == (1000, 2)
    torch.testing.assert_close(exported, expected, rtol=0, atol=1e-6)
    description = {"sg_torchrl.json": ""}
    torch.export.load(target, extra_files=description)
    assert json.loads(description["sg_torchrl.json"])["in_keys"] == ["observation"]


def test_export_of_a_group_writes_one_file_per_seed(group_run, tmp_path):
    assert cli.main([str(group_run), "--episodes", "0", "--export", str(tmp_path / "p.pt2")]) == 0
    assert sorted(p.name for p in tmp_path.glob("p*.pt2")) == ["p-seed-000.pt2", "p-seed-001.pt2"]


# ---------------------------------------------------------------------------- command line
def test_bad_arguments_exit_2_and_write_nothing(group_run, tmp_path, capsys):
    cases = [
        ([group_run, "--episodes", "-1"], "--episodes must be >= 0"),
        ([group_run, "--seeds", "5"], "seed 5 is not in the run"),
        ([tmp_path / "nowhere"], "no run at"),
        ([group_run, "--video", tmp_path / "v.avi"], ".mp4 or .gif"),
        ([group_run, "--env-options", "no_such_option=1"], "no_such_option"),
        ([group_run, "--env-options", "seed=3"], "cannot set seed"),
        ([group_run, "--episodes", "2", "--video", tmp_path / "v.gif", "--video-episodes", "3"], "more than the 2"),
    ]
    for argv, message in cases:
        code, _, err = run_eval(*argv, capsys=capsys)
        assert code == 2 and message in err, (argv, err)
    assert not (group_run / "eval").exists()
    code, _, err = run_eval(group_run, "--no-such-flag", capsys=capsys)
    assert code == 2 and "sg-eval: error" in err


def test_an_earlier_evaluation_is_kept_unless_overwrite(group_run, capsys):
    assert run_eval(group_run, "--seeds", "0", "--episodes", "1", capsys=capsys)[0] == 0
    first = (group_run / "eval" / "summary.json").read_text()
    code, _, err = run_eval(group_run, "--seeds", "0", "--episodes", "2", capsys=capsys)
    assert code == 2 and "already exist" in err and "--overwrite" in err
    assert (group_run / "eval" / "summary.json").read_text() == first
    assert run_eval(group_run, "--seeds", "0", "--episodes", "2", "--overwrite", capsys=capsys)[0] == 0
    assert json.loads((group_run / "eval" / "summary.json").read_text())["episodes"] == 2


def test_an_unwritable_output_exits_3(group_run, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    code, _, err = run_eval(group_run, "--seeds", "0", "--episodes", "1", "--output-dir", blocker / "eval",
                            capsys=capsys)
    assert code == 3 and "cannot write" in err and "is a file" in err


def test_the_command_runs_as_a_module(group_run):
    result = subprocess.run([sys.executable, "-m", "sg_torchrl.evaluation.cli", "--help"], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0 and "sg-eval" in result.stdout and "--export" in result.stdout


# ---------------------------------------------------------------------------- videos (need OpenGL)
def test_video_shows_the_evaluated_episodes_with_their_cost(backend, group_run, tmp_path):
    import imageio.v2 as imageio

    base = [str(group_run), "--seeds", "0", "--episodes", "2", "--env-options", "max_episode_steps=60"]
    assert cli.main([*base, "--output-dir", str(tmp_path / "plain")]) == 0
    video = tmp_path / "watch.gif"
    assert cli.main([*base, "--output-dir", str(tmp_path / "video"), "--video", str(video), "--video-episodes", "2",
                     "--video-size", "48", "32"]) == 0
    # Rendering only reads the simulators: the figures are those of the evaluation without a video.
    assert (json.loads((tmp_path / "video" / "summary.json").read_text())["seeds"]
            == json.loads((tmp_path / "plain" / "summary.json").read_text())["seeds"])
    frames = imageio.mimread(video, memtest=False)
    assert len(frames) == 59  # a frame after every step but the last of the 60-step episodes
    assert frames[0].shape[:2] == (32, 2 * 48)  # two episodes side by side
    band = frames[-1][:14, :, :3]
    assert (band == 0).mean() > 0.5 and (band > 200).any()  # the caption: white text on a black band
    assert frames[0][20:].std() > 5  # below it, a picture
    mp4 = tmp_path / "watch.mp4"
    assert cli.main([*base, "--output-dir", str(tmp_path / "mp4"), "--video", str(mp4)]) == 0
    reader = imageio.get_reader(mp4)
    assert reader.count_frames() == 59 and reader.get_data(0).shape == (256, 256, 3)
    reader.close()
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary files were renamed over their targets


def test_mp4_needs_imageio_ffmpeg(group_run, tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    code, _, err = run_eval(group_run, "--video", tmp_path / "v.mp4", capsys=capsys)
    assert code == 2 and "imageio-ffmpeg" in err and ".gif" in err


def test_a_pixel_run_loads_evaluates_and_exports(backend, tmp_path):
    options = {"obs_mode": "vector+rgb", "image_size": 36, "max_episode_steps": 100}
    cfg = TrainConfig(algo="ppo_lag", env_id="SafetyPointGoal1-v0", env_options=options,
                      seed=0, total_steps=200, steps_per_epoch=100, num_envs=2, update_iters=1, minibatch_size=50,
                      eval_episodes=1, wandb="disabled", progress=False, output_dir=str(tmp_path), run_name="pixels")
    train(cfg)
    assert cli.main([str(cfg.run_dir), "--export", str(tmp_path / "pixels.pt2")]) == 0
    summary = json.loads((cfg.run_dir / "eval" / "summary.json").read_text())
    own = json.loads((cfg.run_dir / "summary.json").read_text())
    for name in EVAL_METRICS:
        assert summary["seeds"]["0"][name] == own[name], name
    policy = load_policy(cfg.run_dir)
    assert policy.in_keys == ["pixels", "observation"]
    env = sg_torchrl.make("SafetyPointGoal1-v0", num_envs=3, seed=1, **cfg.env_options)
    td = env.reset()
    actions = policy(td.clone())["action"]
    np.testing.assert_allclose(policy.act({key: td[key][0].numpy() for key in policy.in_keys}), actions[0].numpy(),
                               rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="mapping"):
        policy.act(td["observation"].numpy())
    program = torch.export.load(tmp_path / "pixels.pt2").module()
    torch.testing.assert_close(program(*(td[key] for key in policy.in_keys)), actions, rtol=0, atol=1e-6)
