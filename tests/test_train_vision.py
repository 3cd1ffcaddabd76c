"""sg-train from pixels: CNN actor and critics, tiny runs on pixel envs, exact resume, evaluation, errors.

Tests that build a pixel env need an OpenGL backend (EGL or OSMesa through Mesa, no GPU needed):
without one they skip with the reason :func:`~sg_torchrl.envs.rendering.gl_backend` gives (the
pattern of ``tests/test_vision.py``). The encoder's arithmetic, the layout and the option errors are
tested on synthetic tensors, without drawing. Episodes are cut to 25 steps so that tiny epochs
finish some.
"""

from __future__ import annotations

import contextlib
import csv
import importlib.util
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded

torch.set_num_threads(1)

import sg_torchrl  # noqa: E402
from sg_torchrl.envs import rendering  # noqa: E402
from sg_torchrl.envs.rendering import RenderingUnavailable  # noqa: E402
from sg_torchrl.train import OnPolicyGroupTrainer, TrainConfig, main  # noqa: E402
from sg_torchrl.train.checkpoint import load_checkpoint  # noqa: E402
from sg_torchrl.train.command_line import parse_args  # noqa: E402
from sg_torchrl.train.fused import SeedBatch  # noqa: E402
from sg_torchrl.modules.cnn import DEFAULT_CNN  # noqa: E402
from sg_torchrl.modules.mlp import (  # noqa: E402
    DEPTH_RANGE,
    EncodedMLP,
    ObservationEncoder,
    ObservationLayout,
    forward_in_chunks,
    make_actor_critics,
    make_value,
    write_values,
)
from sg_torchrl.train.seed_runs import seed_entry  # noqa: E402
from sg_torchrl.modules.stacked import StackedActorCritic, in_chunks  # noqa: E402
from trainer_checks import assert_same_state  # noqa: E402

VISION_ID = "SafetyPointGoal1Vision-v0"
#: (env id, env options), all with 64 x 64 images (the ids' default 256 would make training 16 times
#: slower): the Vision id pixels only (RGB), in its default layout (the flat vector and RGB, as
#: Safety-Gymnasium's), and the plain id with the flat vector, RGB and depth.
PIXEL_ENVS = {
    "rgb": (VISION_ID, {"obs_mode": "rgb", "image_size": 64}),
    "vector+rgb": (VISION_ID, {"image_size": 64}),
    "vector+rgbd": ("SafetyPointGoal1-v0", {"obs_mode": "vector+rgbd", "image_size": 64}),
}


def tiny_config(tmp_path, mode: str, **overrides) -> TrainConfig:
    env_id, options = PIXEL_ENVS[mode]
    values = dict(
        env_id=env_id, env_options={**options, "max_episode_steps": 25}, num_envs=2, steps_per_epoch=40,
        total_steps=120, update_iters=2, minibatch_size=32, eval_episodes=0, wandb="disabled", progress=False,
        output_dir=str(tmp_path), run_name="run", checkpoint_every=100,
    )
    values.update(overrides)
    return TrainConfig(**values)


#: ``sg-train`` flags of three 40-step PPO-Lag epochs on the Vision id's default layout (vector and RGB).
CLI_FLAGS = ["--algo", "ppo_lag", "--env-id", VISION_ID, "--env-options", "image_size=64", "max_episode_steps=25",
             "--num-envs", "2", "--steps-per-epoch", "40", "--total-steps", "120", "--update-iters", "2",
             "--minibatch-size", "32", "--eval-episodes", "0", "--wandb", "disabled", "--progress", "false",
             "--checkpoint-every", "1"]


# ---------------------------------------------------------------------------- no OpenGL needed
def pixel_spec(n: int = 2, size: int = 64, vector: int | None = None, depth: bool = False) -> Composite:
    entries = {"pixels": Bounded(0, 255, shape=(n, size, size, 3), dtype=torch.uint8)}  # channels last, as emitted
    if depth:
        entries["depth"] = Bounded(0.0, 42.0, shape=(n, size, size, 1), dtype=torch.float32)
    if vector is not None:
        entries["observation"] = Unbounded(shape=(n, vector))
    entries["cost"] = Unbounded(shape=(n, 1))
    return Composite(**entries, shape=(n,))


class TestLayoutAndEncoder:
    def test_layout_from_the_observation_spec(self):
        layout = ObservationLayout.from_spec(pixel_spec(vector=12, depth=True))
        assert layout == ObservationLayout(vector_dim=12, image_shape=(64, 64), rgb=True, depth=True)
        assert layout.in_keys == ["pixels", "depth", "observation"] and layout.chunk_size is not None
        vector = ObservationLayout.from_spec(Composite(observation=Unbounded(shape=(2, 5)), shape=(2,)))
        assert vector.in_keys == ["observation"] and not vector.images and vector.chunk_size is None
        with pytest.raises(ValueError, match="nothing the networks can read"):
            ObservationLayout.from_spec(Composite(cost=Unbounded(shape=(2, 1)), shape=(2,)))

    def test_layout_rejects_channels_first_images(self):
        # E.g. a spec after ToTensorImage: float (3, H, W) images the encoder would scale twice.
        spec = Composite(pixels=Bounded(0.0, 1.0, shape=(2, 3, 64, 64)), shape=(2,))
        with pytest.raises(ValueError, match="channels-last"):
            ObservationLayout.from_spec(spec)

    def test_encoder_scales_pixels_and_depth_then_appends_the_vector(self):
        torch.manual_seed(0)
        encoder = ObservationEncoder(ObservationLayout(vector_dim=3, image_shape=(64, 64), rgb=True, depth=True))
        pixels = torch.randint(0, 256, (4, 64, 64, 3), dtype=torch.uint8)  # channels last, as the envs emit
        depth = torch.rand(4, 64, 64, 1) * 10.0  # half of it beyond DEPTH_RANGE: saturates at 1
        vector = torch.randn(4, 3)
        expected_input = torch.cat([pixels.float() / 255.0, depth.clamp(max=DEPTH_RANGE) / DEPTH_RANGE], dim=-1)
        expected_input = expected_input.permute(0, 3, 1, 2).contiguous()  # what the ConvNet takes
        originals = pixels.clone(), depth.clone()
        features = encoder(pixels, depth, vector)
        assert features.shape == (4, encoder.out_features) == (4, 32 * 4 * 4 + 3)
        torch.testing.assert_close(features, torch.cat([encoder.cnn(expected_input), vector], dim=-1))
        assert torch.equal(pixels, originals[0]) and torch.equal(depth, originals[1])  # inputs are not scaled in place

    def test_images_too_small_for_the_cnn_are_a_clear_error(self):
        assert DEFAULT_CNN.min_image_size == 36 and DEFAULT_CNN.output_side(36) == 1
        assert DEFAULT_CNN.output_side(35) == 0
        with pytest.raises(ValueError, match="at least 36 pixels a side"):
            ObservationEncoder(ObservationLayout(vector_dim=None, image_shape=(32, 32), rgb=True))

    def test_actor_and_critics_have_their_own_encoders(self):
        spec = pixel_spec(vector=7)
        actor, critic, cost_critic = make_actor_critics(spec, Bounded(-1.0, 1.0, shape=(2, 2)), [16])
        assert actor.in_keys == critic.in_keys == cost_critic.in_keys == ["pixels", "observation"]
        ids = [{id(p) for p in m.parameters()} for m in (actor, critic, cost_critic)]
        assert not (ids[0] & ids[1] or ids[0] & ids[2] or ids[1] & ids[2])
        assert isinstance(critic.module, EncodedMLP)

    def test_chunked_values_equal_one_pass_and_fill_both_time_steps(self):
        torch.manual_seed(0)
        layout = ObservationLayout(vector_dim=None, image_shape=(36, 36), rgb=True)
        critic = make_value(layout, [8], "state_value")
        frames = lambda: torch.randint(0, 256, (2, 5, 36, 36, 3), dtype=torch.uint8)  # noqa: E731
        batch = TensorDict({"pixels": frames(), "next": {"pixels": frames()}}, [2, 5])
        whole = forward_in_chunks(critic, batch.reshape(-1), ["pixels"], ["state_value"], None)["state_value"]
        write_values(batch, [critic], chunk_size=3)  # 10 samples in chunks of 3, 3, 3, 1
        assert batch["state_value"].shape == batch["next", "state_value"].shape == (2, 5, 1)
        torch.testing.assert_close(batch["state_value"].reshape(-1, 1), whole)
        torch.testing.assert_close(batch["next", "state_value"], critic(batch["next"].clone())["state_value"])

    @pytest.mark.parametrize("layout", [ObservationLayout(None, (36, 36), rgb=True),
                                        ObservationLayout(5, (40, 40), rgb=True, depth=True)])
    def test_stacked_encoders_are_each_seeds_single_networks(self, layout):
        torch.manual_seed(0)
        singles = [make_actor_critics(layout, Bounded(-1.0, 1.0, shape=(2,)), [16]) for _ in range(3)]
        model = StackedActorCritic.from_single(singles, layout=layout)
        entries = {"pixels": torch.randint(0, 256, (3, 6, *layout.image_shape, 3), dtype=torch.uint8)}
        if layout.depth:
            entries["depth"] = torch.rand(3, 6, *layout.image_shape, 1) * 10.0
        if layout.vector_dim:
            entries["observation"] = torch.randn(3, 6, layout.vector_dim)
        obs = TensorDict(entries, [3, 6])
        loc, scale = model.dist_params(obs)
        value, cost_value = model.values(obs)
        for seed, (actor, critic, cost_critic) in enumerate(singles):
            inputs = [obs[seed].get(key) for key in layout.in_keys]
            features = model.actor_mean.encoder(obs)[seed]  # one conv2d per seed: the single encoder's, bit for bit
            assert torch.equal(features, actor.module[0].module[0].encoder(*inputs))
            single_loc, single_scale = actor.module[0].module(*inputs)
            torch.testing.assert_close(loc[seed], single_loc, rtol=0, atol=1e-6)  # the heads' matmuls: rounding
            torch.testing.assert_close(scale[seed].expand_as(single_scale), single_scale)
            torch.testing.assert_close(value[seed], critic.module(*inputs).squeeze(-1), rtol=0, atol=1e-6)
            torch.testing.assert_close(cost_value[seed], cost_critic.module(*inputs).squeeze(-1), rtol=0, atol=1e-6)
        chunked = in_chunks(model.values, obs, 4)  # 6 samples in chunks of 4 and 2 (matmuls of other sizes round apart)
        torch.testing.assert_close(chunked, (value, cost_value), rtol=0, atol=1e-6)
        exported = model.export_seed(2, Bounded(-1.0, 1.0, shape=(2,)))
        for mine, theirs in zip(exported, singles[2]):
            for a, b in zip(mine.parameters(), theirs.parameters(), strict=True):
                assert torch.equal(a, b)
        assert model.actor_rows(torch.tensor([1])).layout == layout

    def test_seed_batches_keep_images_apart_in_uint8(self):
        pixels = torch.randint(0, 256, (2, 5, 36, 36, 3), dtype=torch.uint8)
        obs = TensorDict({"pixels": pixels, "observation": torch.randn(2, 5, 4)}, [2, 5])
        batch = SeedBatch.pack({"observation": obs, "advantage": torch.randn(2, 5)})
        assert batch.data.shape == (2, 5, 5) and batch.field_names == ("observation", "advantage")
        index = torch.tensor([[4, 0], [1, 3]])
        minibatch = batch[index].fields()
        assert minibatch["observation"]["pixels"].dtype == torch.uint8
        for seed in range(2):
            assert torch.equal(minibatch["observation"]["pixels"][seed], pixels[seed, index[seed]])
            assert torch.equal(minibatch["observation"]["observation"][seed], obs["observation"][seed, index[seed]])
            assert torch.equal(minibatch["advantage"][seed, :, 0], batch["advantage"][seed, index[seed], 0])
        only_images = SeedBatch.pack({"observation": obs.exclude("observation"), "advantage": torch.randn(2, 5)})
        assert only_images.names == ("advantage",) and only_images.field_names == ("advantage", "observation")
        assert only_images[index].fields()["observation"].keys() == {"pixels"}

    def test_vision_preset_is_ppo_lag_on_a_vision_id_in_whole_epochs(self):
        cfg = parse_args(["--preset", "vision"])
        assert (cfg.algo, cfg.env_id) == ("ppo_lag", VISION_ID) and cfg.env_id in sg_torchrl.list_envs()
        assert cfg.total_steps % cfg.steps_per_epoch == 0 and cfg.steps_per_epoch % cfg.num_envs == 0
        assert cfg.steps_per_epoch // cfg.num_envs >= 1000  # every simulator finishes an episode per epoch

    def test_vision_ids_get_the_papers_network_sizes_per_robot(self):
        # The MLP after the encoder: [256, 256] for the Ant and Doggo navigation robots, as their vector ids.
        assert TrainConfig(env_id="SafetyDoggoGoal1Vision-v0").network_sizes == [256, 256]
        assert TrainConfig(env_id=VISION_ID).network_sizes == [64, 64]

    def test_cli_reports_an_image_size_too_small_for_the_cnn(self, capsys):
        assert main(["--preset", "vision", "--env-options", "image_size=24"]) == 2
        assert "image_size=24 is too small for sg-train's CNN encoder" in capsys.readouterr().err


# ---------------------------------------------------------------------------- pixel envs (OpenGL)
def test_cnn_actor_and_critics_on_a_vision_rollout(backend):
    # The Vision id's default layout (the flat vector and RGB), at a small size.
    env = sg_torchrl.make(VISION_ID, num_envs=2, seed=0, image_size=64)
    assert ObservationLayout.from_spec(env.observation_spec) == ObservationLayout(60, (64, 64), rgb=True)
    actor, critic, cost_critic = make_actor_critics(env.observation_spec, env.action_spec, [64, 64])
    rollout = env.rollout(3, actor)
    env.close()
    assert rollout.batch_size == (2, 3) and rollout["pixels"].dtype == torch.uint8
    assert rollout["pixels"].shape == (2, 3, 64, 64, 3) and rollout["observation"].shape == (2, 3, 60)
    assert rollout["action"].shape == rollout["loc"].shape == rollout["scale"].shape == (2, 3, 2)
    assert rollout["action_log_prob"].shape == (2, 3)
    critic(rollout)
    cost_critic(rollout)
    assert rollout["state_value"].shape == rollout["cost_value"].shape == (2, 3, 1)
    assert torch.isfinite(rollout["state_value"]).all() and torch.isfinite(rollout["cost_value"]).all()


def cli(argv: list[str]) -> None:
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv) == 0


def progress_rows(run_dir: Path) -> list[dict[str, float]]:
    """``progress.csv``'s epoch rows as numbers, without their timings (``Time/*``)."""
    with (run_dir / "progress.csv").open() as handle:
        return [{k: float(v) for k, v in row.items() if not k.startswith("Time/")} for row in csv.DictReader(handle)]


@pytest.fixture(scope="module")
def group_runs(tmp_path_factory) -> Path:
    """Three epochs of ``--seeds 0 1`` (vector and RGB) uninterrupted and in two processes, and ``--seed 1`` alone."""
    if importlib.util.find_spec("mujoco") is None:  # pragma: no cover
        pytest.skip("no MuJoCo")
    try:
        rendering.gl_backend()
    except RenderingUnavailable as error:
        pytest.skip(f"no OpenGL backend for headless rendering: {error}")
    root = tmp_path_factory.mktemp("vision_groups")
    cli([*CLI_FLAGS, "--seeds", "0", "1", "--output-dir", str(root), "--run-name", "whole"])
    cli([*CLI_FLAGS, "--seed", "1", "--output-dir", str(root), "--run-name", "single"])
    interrupted = OnPolicyGroupTrainer(parse_args([*CLI_FLAGS, "--seeds", "0", "1", "--output-dir", str(root),
                                                   "--run-name", "resumed"]))
    interrupted.run(max_epochs=2)  # stopped after two of its three epochs, checkpointed
    interrupted.base_env.close()
    cli(["--resume", str(root / "resumed")])
    return root


def test_a_group_seed_is_its_single_seed_run(group_runs):
    # Epoch 1's trajectories are the same and its update agrees to float rounding (the encoders are the
    # single ones bit for bit, the MLP heads' batched matmuls sum in another order for S = 2 and S = 1);
    # later epochs act on those rounded networks, so their figures drift apart by a little more.
    group, single = progress_rows(group_runs / "whole" / "seed-001"), progress_rows(group_runs / "single")
    assert len(group) == len(single) == 3
    assert group[0]["Metrics/EpochEpCost"] == single[0]["Metrics/EpochEpCost"]
    for epoch, (mine, alone) in enumerate(zip(group, single), start=1):
        assert mine.keys() == alone.keys()
        rel, abs_ = (1e-4, 1e-6) if epoch == 1 else (1e-3, 1e-4)
        for name in mine:
            assert mine[name] == pytest.approx(alone[name], rel=rel, abs=abs_, nan_ok=True), (epoch, name)
    mine, alone = seed_entry(load_checkpoint(group_runs / "whole"), 1), load_checkpoint(group_runs / "single")
    alone = seed_entry(alone, 1)
    for network in ("actor", "critic", "cost_critic"):
        for key, value in mine["networks"][network].items():
            torch.testing.assert_close(value, alone["networks"][network][key], rtol=0, atol=1e-3)


def test_a_resumed_group_continues_bit_for_bit(group_runs):
    whole, resumed = load_checkpoint(group_runs / "whole"), load_checkpoint(group_runs / "resumed")
    assert resumed["epoch"] == whole["epoch"] == 3
    assert_same_state(resumed["seeds"], whole["seeds"], "seeds")
    assert_same_state(resumed["collector"], whole["collector"], "collector")
    for seed in ("seed-000", "seed-001"):
        assert_same_state(progress_rows(group_runs / "resumed" / seed), progress_rows(group_runs / "whole" / seed))


@pytest.mark.parametrize("mode", ["rgb", "vector+rgbd"])
def test_a_single_seed_learns_from_pixels_and_evaluates(backend, tmp_path, mode):
    trainer = OnPolicyGroupTrainer(tiny_config(tmp_path, mode))
    assert (trainer.obs_norm is None) == (mode == "rgb")  # the normaliser is for the flat vector only
    assert trainer.model.layout.images and trainer.model.chunk_size is not None
    actor_before = trainer.model.flat_actor.clone()
    trainer.run()
    moved = (trainer.model.flat_actor != actor_before).any(0)
    conv = trainer.model.actor_mean.encoder.conv.weights[0][0].numel()
    assert moved[:conv].any()  # the actor's first convolution learns (its weights lead the flat buffer)
    trainer.cfg.eval_episodes = 2
    evaluation = trainer._evaluate_seed(0)
    assert evaluation["Metrics/EvalEpLen"] == 25.0
    assert evaluation["Metrics/EvalEpRet"] == evaluation["Metrics/EvalEpRet"]  # not NaN
    trainer.base_env.close()


@pytest.mark.parametrize("algo", ["cup", "cpo"])
def test_two_stage_and_trust_region_updates_train_the_cnns(backend, tmp_path, algo):
    # CUP's stage-one policy and CPO's whole-batch trust-region step read the images too, in a group.
    trainer = OnPolicyGroupTrainer(tiny_config(tmp_path, "rgb", algo=algo, cost_limit=0.0, total_steps=40,
                                               seeds=[0, 1]))
    model = trainer.model
    before = model.flat_actor.clone(), model.flat_critics.clone()
    metrics = trainer.train_epoch()
    assert (model.flat_actor != before[0]).any(1).all() and (model.flat_critics != before[1]).any(1).all()
    for name in ("Train/KL", "Loss/Loss_reward_critic", "Loss/Loss_cost_critic"):
        assert torch.isfinite(torch.tensor(metrics[name])), name
    trainer.base_env.close()


def test_vision_recipe_runs(backend):
    root = Path(__file__).resolve().parents[1]
    example = root / "examples" / "vision.py"
    args = ["--obs-mode", "vector+rgbd", "--max-episode-steps", "25", "--total-steps", "100", "--steps-per-epoch",
            "50", "--num-envs", "2", "--update-iters", "2"]
    # This tree's sg_torchrl, whichever one the interpreter has installed.
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    result = subprocess.run([sys.executable, str(example), *args], capture_output=True, text=True, timeout=110,
                            env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [line for line in result.stdout.splitlines() if line.startswith("epoch ")]
    assert len(lines) == 2 and "EpCost" in lines[-1] and "nan" not in lines[-1].lower()
