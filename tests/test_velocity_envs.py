"""Velocity-constrained locomotion envs: gymnasium-v4 parity, cost semantics and SafeEnv behaviour.

The gymnasium oracle steps gymnasium's own ``<Robot>-v4`` env next to ours from the same state with
the same actions, so observation layout, reward, termination and velocity measurement are checked
against the reference implementation rather than against numbers copied into the test.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import Compose, StepCounter, TransformedEnv, VecNormV2
from torchrl.envs.utils import check_env_specs

import sg_torchrl
from sg_torchrl.envs import EpisodeSum
from sg_torchrl.envs.velocity import ROBOTS

torch.set_num_threads(1)

ROBOT_NAMES = sorted(ROBOTS)


# ---------------------------------------------------------------------------- helpers
def velocity_id(robot: str, version: int = 1) -> str:
    return f"Safety{robot}Velocity-v{version}"


def make_env(env_id: str = "SafetyHalfCheetahVelocity-v1", num_envs: int = 1, seed: int = 0, **options):
    return sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, **options)


def action_td(env, action) -> TensorDict:
    """An input TensorDict holding ``action`` (array-like, ``(N, act_dim)``)."""
    return TensorDict({"action": torch.as_tensor(np.asarray(action), dtype=torch.float32)}, batch_size=env.batch_size)


def random_actions(env, steps: int, seed: int, scale: float = 1.0) -> torch.Tensor:
    """``(steps, N, act_dim)`` actions uniform in ``scale`` times the action bounds."""
    generator = torch.Generator().manual_seed(seed)
    low, high = env.action_spec.space.low, env.action_spec.space.high
    mid, half = (high + low) / 2, (high - low) / 2 * scale
    return mid + half * (2 * torch.rand((steps, *low.shape), generator=generator) - 1)


def place(env, index: int, qpos: np.ndarray | None = None, qvel: np.ndarray | None = None) -> None:
    """Put simulator ``index`` in the given joint state (defaults: the model's rest pose, at rest)."""
    model = env.physics.model
    qpos = model.qpos0.copy() if qpos is None else qpos
    qvel = np.zeros(model.nv) if qvel is None else qvel
    env.physics.reset([index], qpos[None], qvel[None])


def run_sim0(env, actions: torch.Tensor, steps: int) -> list[TensorDict]:
    """Step with ``step_and_maybe_reset``; per step, simulator 0's transition and next root td."""
    out = []
    td = env.reset()
    for t in range(steps):
        td.set("action", actions[t, : env.num_envs])
        stepped, td = env.step_and_maybe_reset(td)
        out.append(TensorDict({"step": stepped[0].clone(), "root": td[0].clone()}))
    return out


# ---------------------------------------------------------------------------- gymnasium oracle
@pytest.mark.parametrize("robot", ROBOT_NAMES)
class TestGymnasiumOracle:
    """Our env and gymnasium's ``<Robot>-v4`` agree step by step from the same state."""

    steps = 30

    def test_matches_gymnasium_v4(self, robot):
        reference = gymnasium.make(f"{robot}-v4").unwrapped
        reference.reset(seed=7)
        env = make_env(velocity_id(robot), num_envs=1)
        env.reset()
        place(env, 0, reference.data.qpos.copy(), reference.data.qvel.copy())
        # Out-of-range actions included (1.2x the bounds): both clamp inside MuJoCo, both penalise the
        # action as given. float32-representable, so both sides see the same numbers.
        actions = random_actions(env, self.steps, seed=1, scale=1.2)
        assert (actions.abs() > env.action_spec.space.high).any()
        spec = ROBOTS[robot]
        for t in range(self.steps):
            ref_obs, ref_reward, ref_terminated, _, info = reference.step(actions[t, 0].double().numpy())
            td = env.step(action_td(env, actions[t]))["next"]
            np.testing.assert_allclose(td["observation"][0].numpy(), ref_obs, rtol=1e-4, atol=1e-5,
                                       err_msg=f"observation, step {t}")
            np.testing.assert_allclose(td["reward"].item(), ref_reward, rtol=1e-4, atol=1e-5,
                                       err_msg=f"reward, step {t}")
            assert td["terminated"].item() == ref_terminated, f"terminated, step {t}"
            # Safety-Gymnasium measures gymnasium's velocity: planar speed or signed x velocity.
            if 1 in spec.planar_cost_versions:
                speed = np.hypot(info["x_velocity"], info["y_velocity"])
            else:
                speed = info["x_velocity"]
            np.testing.assert_allclose(env.last_velocity[0], speed, rtol=1e-6, atol=1e-8)
            assert td["cost"].item() == float(speed > env.velocity_threshold)
            if ref_terminated:
                break
        reference.close()
        assert t >= 9, f"only {t + 1} steps compared"  # the comparison covered a real trajectory


# ---------------------------------------------------------------------------- cost semantics
class TestVelocityCost:
    def test_thresholds_from_reference(self):
        # reference/safety_gymnasium_semantics.md, section 8.
        assert make_env("SafetyHalfCheetahVelocity-v1").velocity_threshold == 3.2096
        assert make_env("SafetyHalfCheetahVelocity-v0").velocity_threshold == 2.8795
        assert make_env("SafetyHumanoidVelocity-v1").velocity_threshold == 1.4149
        assert make_env("SafetySwimmerVelocity-v0").velocity_threshold == 0.04845

    @pytest.mark.parametrize("env_id", sg_torchrl.list_envs(family="velocity"))
    def test_cost_of_velocity(self, env_id):
        # The cost hook on measured (x, 0) velocities, batched and on one simulator (its own branch).
        batch, single = make_env(env_id, num_envs=4), make_env(env_id)
        threshold = batch.velocity_threshold
        batch._velocity[:] = [[0.0, 0.0], [0.5 * threshold, 0.0], [1.01 * threshold, 0.0], [10 * threshold, 0.0]]
        np.testing.assert_array_equal(batch._compute_cost()["velocity"], [0.0, 0.0, 1.0, 1.0])
        single._velocity[:] = [[threshold, 0.0]]
        assert single._compute_cost()["velocity"].tolist() == [0.0]  # strictly above the threshold costs

    @staticmethod
    def step_from_velocity(env_id: str, qvel_entries: dict[int, float]) -> tuple[float, float, float]:
        """One zero-action step from the rest pose with the given root velocities.

        Returns (measured velocity, cost, ("cost_info", "velocity")).
        """
        env = make_env(env_id)
        env.reset()
        qvel = np.zeros(env.physics.model.nv)
        for index, value in qvel_entries.items():
            qvel[index] = value
        place(env, 0, qvel=qvel)
        td = env.step(action_td(env, np.zeros((1, env.action_dim))))["next"]
        return float(env.last_velocity[0]), td["cost"].item(), td["cost_info", "velocity"].item()

    @pytest.mark.parametrize("robot", ["HalfCheetah", "Hopper", "Walker2d", "Swimmer"])
    def test_signed_forward_velocity(self, robot):
        # qvel[0] is the root's x slide joint for these planar robots; v1 uses the signed x velocity.
        env_id = velocity_id(robot, 1)
        threshold = ROBOTS[robot].thresholds[1]
        speed, cost, cost_info = self.step_from_velocity(env_id, {0: 3 * threshold})
        assert speed > threshold and cost == 1.0 and cost_info == 1.0
        speed, cost, cost_info = self.step_from_velocity(env_id, {0: 0.3 * threshold})
        assert 0 < speed < threshold and cost == 0.0 and cost_info == 0.0
        # Running backwards fast is not a violation of a signed-velocity constraint.
        speed, cost, _ = self.step_from_velocity(env_id, {0: -3 * threshold})
        assert speed < -threshold and cost == 0.0

    def test_swimmer_v0_uses_planar_speed(self):
        threshold = ROBOTS["Swimmer"].thresholds[0]
        speed, cost, _ = self.step_from_velocity("SafetySwimmerVelocity-v0", {0: -10 * threshold})
        assert speed > threshold and cost == 1.0
        speed, cost, _ = self.step_from_velocity("SafetySwimmerVelocity-v0", {1: 10 * threshold})
        assert speed > threshold and cost == 1.0

    @pytest.mark.parametrize("robot", ["Ant", "Humanoid"])
    @pytest.mark.parametrize("version", [0, 1])
    def test_planar_speed(self, robot, version):
        # Free joint: qvel[0:2] is the root's (x, y) velocity. Sideways motion costs too.
        env_id = velocity_id(robot, version)
        threshold = ROBOTS[robot].thresholds[version]
        speed, cost, _ = self.step_from_velocity(env_id, {1: 2 * threshold})
        assert speed > threshold and cost == 1.0
        speed, cost, _ = self.step_from_velocity(env_id, {0: -2 * threshold})
        assert speed > threshold and cost == 1.0
        speed, cost, _ = self.step_from_velocity(env_id, {0: 0.2 * threshold, 1: 0.2 * threshold})
        assert 0 < speed < threshold and cost == 0.0

    def test_raw_cost_mode(self):
        env = make_env("SafetyHalfCheetahVelocity-v1", num_envs=2, cost_mode="raw")
        rollout = env.rollout(5)
        assert set(rollout["next", "cost"].unique().tolist()) <= {0.0, 1.0}


# ---------------------------------------------------------------------------- seeding
class TestSeeding:
    @pytest.mark.parametrize("env_id", ["SafetyHalfCheetahVelocity-v1", "SafetyHopperVelocity-v1"])
    def test_simulator_zero_independent_of_batch_size(self, env_id):
        # 12 steps with 5-step episodes: two auto-resets of simulator 0 inside step_and_maybe_reset.
        steps = 12
        small = make_env(env_id, num_envs=1, seed=11, max_episode_steps=5)
        large = make_env(env_id, num_envs=8, seed=11, max_episode_steps=5)
        actions = random_actions(large, steps, seed=3)  # simulator 0 gets the same actions in both
        a, b = run_sim0(small, actions, steps), run_sim0(large, actions, steps)
        keys = [("step", "observation"), ("step", "next", "observation"), ("step", "next", "reward"),
                ("step", "next", "cost"), ("step", "next", "done"), ("step", "next", "terminated"),
                ("step", "next", "truncated"), ("root", "observation")]
        for t, (x, y) in enumerate(zip(a, b)):
            for key in keys:
                torch.testing.assert_close(x[key], y[key], rtol=0, atol=0, msg=f"{key} differs at step {t}")
        assert a[4]["step", "next", "truncated"].item()  # an auto-reset did happen

    def test_different_seeds_differ(self):
        first = make_env(num_envs=2, seed=0).reset()["observation"]
        again = make_env(num_envs=2, seed=0).reset()["observation"]
        other = make_env(num_envs=2, seed=1).reset()["observation"]
        torch.testing.assert_close(first, again, rtol=0, atol=0)
        assert not torch.equal(first[0], other[0])
        assert not torch.equal(first[0], first[1])  # simulators of one env differ too

    def test_set_seed_restarts_generators(self):
        env = make_env(num_envs=2, seed=5)
        first = env.reset()["observation"]
        env.set_seed(5)
        torch.testing.assert_close(env.reset()["observation"], first, rtol=0, atol=0)


# ---------------------------------------------------------------------------- resets and time limits
class TestPartialReset:
    def test_only_masked_simulators_reset(self):
        env = make_env(num_envs=4, seed=2, max_episode_steps=5)
        td = env.reset()
        for action in random_actions(env, 3, seed=0):
            td = env.step(td.set("action", action))["next"].clone()
        qpos_before = env.physics.qpos().copy()
        mask = torch.tensor([True, False, True, False])
        fresh = make_env(num_envs=4, seed=2).reset()["observation"]  # what a first reset gives
        out = env.reset(td.clone().set("_reset", mask[:, None]))
        keep = ~mask
        np.testing.assert_array_equal(env.physics.qpos()[keep.numpy()], qpos_before[keep.numpy()])
        torch.testing.assert_close(out["observation"][keep], td["observation"][keep], rtol=0, atol=0)
        # Reset simulators draw their second initial state from their own generators.
        assert not torch.equal(out["observation"][mask], fresh[mask])
        assert not np.allclose(env.physics.qpos()[mask.numpy()], qpos_before[mask.numpy()])
        assert env._elapsed.tolist() == [0, 3, 0, 3]
        assert not out["done"].any()
        # The step counters carried on: the kept simulators hit the 5-step limit two steps later.
        for action in random_actions(env, 2, seed=1):
            nxt = env.step(out.set("action", action))["next"]
            out = nxt.clone()
        assert nxt["truncated"].squeeze(-1).tolist() == [False, True, False, True]

    @pytest.mark.parametrize("input_keys", [("observation", "cost", "done", "action"), ("done",), ()])
    def test_partial_reset_merge_matches_torchrl(self, input_keys):
        """SafeEnv's one-``torch.where``-per-entry merge gives TorchRL's ``TensorDict.where`` result,
        including entries present on one side only (0 in the rows where they are missing)."""
        fast, general = make_env(num_envs=4, seed=3), make_env(num_envs=4, seed=3)
        general.run_type_checks = True  # takes EnvBase's own _reset_proc_data
        mask = torch.tensor([[False], [True], [False], [True]])
        results = []
        for env in (fast, general):
            td = env.reset()
            td = env.step(td.set("action", random_actions(env, 1, seed=0)[0]))["next"].clone()
            td["action"] = torch.ones(4, env.action_dim)
            results.append(env.reset(td.select(*input_keys).set("_reset", mask)))
        assert set(results[0].keys(True, True)) == set(results[1].keys(True, True))
        for key in results[1].keys(True, True):
            torch.testing.assert_close(results[0][key], results[1][key], rtol=0, atol=0, msg=str(key))

    def test_reset_resets_only_done_in_step_and_maybe_reset(self):
        env = make_env(num_envs=3, seed=0, max_episode_steps=2)
        td = env.reset()
        for action in random_actions(env, 2, seed=0):
            stepped, td = env.step_and_maybe_reset(td.set("action", action))
        assert stepped["next", "truncated"].all()
        assert env._elapsed.tolist() == [0, 0, 0]
        assert not td["done"].any()


class TestSnapshots:
    @pytest.mark.parametrize("robot", ["Ant", "HalfCheetah"])
    def test_state_loaded_into_a_fresh_env_replays_bit_for_bit(self, robot):
        # Resume starts from a new env: every input of the next step (the constraint solver's warm
        # start included) must travel with the snapshot, or contacts drift by solver tolerance.
        env = make_env(velocity_id(robot), num_envs=2, seed=4)
        td = env.reset()
        actions = random_actions(env, 120, seed=2)
        for action in actions[:20]:
            td = env.step(td.set("action", action))["next"].clone()
        fresh = make_env(velocity_id(robot), num_envs=2, seed=99)
        fresh.reset()
        fresh.load_sim_state(env.sim_state())
        for action in actions[20:]:
            env.step(td.clone().set("action", action))
            fresh.step(td.clone().set("action", action))
            np.testing.assert_array_equal(env.physics.qpos(), fresh.physics.qpos())
            np.testing.assert_array_equal(env.physics.qvel(), fresh.physics.qvel())


class TestTimeLimit:
    def test_truncated_exactly_at_max_episode_steps(self):
        env = make_env(num_envs=2, max_episode_steps=7)
        rollout = env.rollout(7, break_when_any_done=False)
        truncated = rollout["next", "truncated"].squeeze(-1)
        assert truncated[:, :6].sum() == 0
        assert truncated[:, 6].all()
        assert rollout["next", "done"][:, 6].all()
        assert not rollout["next", "terminated"].any()

    def test_rollout_stops_at_time_limit(self):
        env = make_env(num_envs=2, max_episode_steps=7)
        assert env.rollout(50).batch_size == torch.Size([2, 7])


# ---------------------------------------------------------------------------- bad input and isolation
class TestBadInput:
    def test_wrong_action_shape(self):
        env = make_env(num_envs=2)
        env.reset()
        with pytest.raises(ValueError, match=r"expected \(2, 6\)"):
            env.step(action_td(env, np.zeros((2, 5))))

    def test_nan_action_names_simulator(self):
        env = make_env(num_envs=3)
        env.reset()
        action = np.zeros((3, 6))
        action[1, 2] = np.nan
        with pytest.raises(ValueError, match=r"simulators \[1\]"):
            env.step(action_td(env, action))

    def test_inf_action(self):
        env = make_env(num_envs=2)
        env.reset()
        with pytest.raises(ValueError, match=r"non-finite"):
            env.step(action_td(env, np.full((2, 6), np.inf)))

    def test_bad_options(self):
        with pytest.raises(ValueError, match="num_envs"):
            make_env(num_envs=0)
        with pytest.raises(ValueError, match="cost_mode"):
            make_env(cost_mode="bogus")
        with pytest.raises(ValueError, match="max_episode_steps"):
            make_env(max_episode_steps=0)

    def test_unknown_robot_and_version(self):
        from sg_torchrl.envs.velocity import VelocityEnv

        with pytest.raises(ValueError, match="unknown velocity robot"):
            VelocityEnv("Cheetah")
        with pytest.raises(ValueError, match="versions"):
            VelocityEnv("Ant", version=3)


class TestIsolation:
    @pytest.mark.parametrize("corruption", [np.nan, 1e12])  # non-finite, and beyond MuJoCo's mjMAXVAL
    def test_diverged_simulator_is_truncated_and_reset(self, corruption):
        env = make_env(num_envs=3, seed=4)
        twin = make_env(num_envs=3, seed=4)
        actions = random_actions(env, 6, seed=2)
        td, td_twin = env.reset(), twin.reset()
        for t in range(6):
            if t == 3:
                env.physics.datas[1].qvel[:] = corruption
            out = env.step(td.set("action", actions[t]))["next"]
            ref = twin.step(td_twin.set("action", actions[t]))["next"]
            if t == 3:
                assert out["truncated"].squeeze(-1).tolist() == [False, True, False]
                assert out["reward"][1].item() == 0.0 and out["cost"][1].item() == 0.0
                assert env.physics_errors == 1
            for key in ("observation", "reward", "cost", "done"):
                assert torch.isfinite(out[key].float()).all(), key
                torch.testing.assert_close(out[key][[0, 2]], ref[key][[0, 2]], rtol=0, atol=0)
            td, td_twin = out.clone(), ref.clone()
        assert env.physics_errors == 1
        # The diverged simulator restarted an episode from a fresh reset state.
        assert env._elapsed.tolist() == [6, 2, 6]

    def test_divergence_counted_once(self):
        # MuJoCo's warning counter stays raised after its own reset: it must not flag later steps.
        env = make_env(num_envs=2, seed=0)
        td = env.reset()
        env.physics.datas[0].qvel[:] = np.nan
        flags = []
        for action in random_actions(env, 4, seed=0):
            td = env.step(td.set("action", action))["next"].clone()
            flags.append(td["truncated"].squeeze(-1).tolist())
        assert flags == [[True, False]] + [[False, False]] * 3
        assert env.physics_errors == 1

    def test_unstable_simulators_reported_by_physics(self):
        env = make_env(num_envs=3, seed=0)
        env.reset()
        env.physics.datas[2].qpos[:] = np.inf
        unstable = env.physics.step(np.zeros((3, 6)), 5)
        assert unstable.tolist() == [False, False, True]
        assert np.isfinite(env.physics.qpos()).all()  # MuJoCo reset it; the cache shows the reset state
        assert not env.physics.step(np.zeros((3, 6)), 5).any()


# ---------------------------------------------------------------------------- where cost lives
@pytest.mark.filterwarnings("ignore:Support of VecNormV2 for containers with non-empty batch-size")
class TestCostInObservationSpec:
    """``cost`` is declared in the observation spec, so ``reward`` stays the only reward key."""

    @staticmethod
    def transformed(num_envs: int = 4, max_episode_steps: int = 10):
        # Threshold 0: every forward-moving step costs, so episode costs are non-trivial.
        env = make_env(num_envs=num_envs, seed=0, max_episode_steps=max_episode_steps, velocity_threshold=0.0)
        return TransformedEnv(
            env,
            Compose(
                StepCounter(),
                EpisodeSum(in_keys=["reward", "cost"], out_keys=["episode_reward", "episode_cost"]),
                VecNormV2(in_keys=["observation"]),
            ),
        )

    def test_spec_layout(self):
        env = make_env(num_envs=2)
        assert env.reward_key == "reward"
        assert env.reward_keys == ["reward"]
        assert "cost" in env.observation_spec.keys()
        assert ("cost_info", "velocity") in env.observation_spec.keys(include_nested=True)
        assert env.observation_spec["cost"].shape == env.reward_spec.shape
        assert env.observation_spec["cost"].dtype == env.reward_spec.dtype

    def test_transforms_pass_check_env_specs(self):
        env = self.transformed()
        check_env_specs(env, seed=0)
        assert env.reward_key == "reward"

    def test_collector_episode_cost(self):
        num_envs, length, steps = 4, 10, 25
        env = self.transformed(num_envs, length)
        collector = Collector(env, policy=None, frames_per_batch=num_envs * steps, total_frames=num_envs * steps,
                              auto_register_policy_transforms=False)
        batch = next(iter(collector))
        collector.shutdown()
        assert batch.batch_size == torch.Size([num_envs, steps])
        nxt = batch["next"]
        assert (nxt["cost"] > 0).any() and (nxt["cost"] == 0).any()
        episodes = 0
        for i in range(num_envs):
            running_cost = running_reward = 0.0
            for t in range(steps):
                running_cost += nxt["cost"][i, t].item()
                running_reward += nxt["reward"][i, t].item()
                assert nxt["episode_cost"][i, t].item() == pytest.approx(running_cost)
                if nxt["done"][i, t].item():
                    assert nxt["step_count"][i, t].item() == length
                    assert nxt["episode_reward"][i, t].item() == pytest.approx(running_reward, rel=1e-5, abs=1e-4)
                    running_cost = running_reward = 0.0
                    episodes += 1
        assert episodes == num_envs * (steps // length)
        # Normalised observations stay finite.
        assert torch.isfinite(nxt["observation"]).all()

