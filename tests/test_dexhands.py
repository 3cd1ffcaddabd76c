"""Shadow-Hand safety tasks (sg_torchrl.envs.hands): scene, sizes, costs per variant and source, reward, seeding."""

from __future__ import annotations

import filecmp
import os
import sys

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict

import sg_torchrl
from sg_torchrl.envs.hands import PAPER_JOINTS, ShadowHandEnv, build_scene
from sg_torchrl.envs.hands.rotations import quat_multiply, rotation_distance
from sg_torchrl.envs.hands.scene import hand_assets_dir
from seeding_checks import assert_sim0_same_for_any_batch

torch.set_num_threads(1)

IDS = {safety: f"ShadowHandOver{safety}-v0" for safety in ("SafeJoint", "SafeFinger")}
CATCH_IDS = {safety: f"ShadowHandCatchOver2Underarm{safety}-v0" for safety in ("SafeJoint", "SafeFinger")}
TASK_IDS = {"HandOver": IDS, "CatchOver2Underarm": CATCH_IDS}
#: (observation, action) sizes of the paper (section 4.4)
PAPER_SIZES = {"HandOver": (398, 40), "CatchOver2Underarm": (422, 52)}
DEG = np.pi / 180
#: A forefinger pose inside every safe range (abduction 0, knuckle and middle flexion 45 degrees).
SAFE_POSE = {PAPER_JOINTS[4]: 0.0, PAPER_JOINTS[3]: 45 * DEG, PAPER_JOINTS[2]: 45 * DEG}


def make_env(safety: str = "SafeFinger", num_envs: int = 1, seed: int = 0, task: str = "HandOver",
             **options) -> ShadowHandEnv:
    return sg_torchrl.make(TASK_IDS[task][safety], num_envs=num_envs, seed=seed, **options)


def axis_angle(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return np.concatenate(([np.cos(angle / 2)], np.sin(angle / 2) * axis))


def place(env: ShadowHandEnv, index: int, joints: dict[str, float] | None = None, hand: int = 0,
          ball_pos=None, ball_quat=None) -> None:
    """Put simulator ``index`` in a constructed state: every hand's forefinger in :data:`SAFE_POSE`, then
    ``joints`` (unprefixed names) of hand ``hand``, and the ball pose."""
    physics = env.physics
    qpos, qvel = physics.qpos()[index].copy(), np.zeros(physics.model.nv)
    layout = env.layout
    for h, layout_hand in enumerate(layout.hands):
        for name, angle in {**SAFE_POSE, **(joints if h == hand and joints else {})}.items():
            qpos[layout_hand.qpos_index(name)] = angle
    if ball_pos is not None:
        qpos[layout.ball_qpos:layout.ball_qpos + 3] = ball_pos
    if ball_quat is not None:
        qpos[layout.ball_qpos + 3:layout.ball_qpos + 7] = ball_quat
    physics.reset([index], qpos[None], qvel[None])


# ---------------------------------------------------------------------------- scene
class TestScene:
    def test_two_hands_of_twenty_four_joints_and_twenty_actuators(self):
        model, layout = build_scene()
        assert [hand.prefix for hand in layout.hands] == ["right/", "left/"]
        for hand in layout.hands:
            assert len(hand.qpos) == 24 and len(hand.actuators) == 20
        # Two hands (24 hinge joints each) plus the ball's free joint; one mocap goal.
        assert (model.nq, model.nv, model.nu, model.nmocap) == (48 + 7, 48 + 6, 40, 1)

    def test_built_once_and_shared_by_every_simulator(self):
        a, b = make_env(num_envs=2), make_env(num_envs=3)
        assert a.physics.model is b.physics.model is build_scene()[0]

    def test_second_hand_faces_the_first(self):
        env = make_env()
        model = env.physics.model
        data = env.physics.datas[0]
        right, left = (data.body(f"{prefix}robot0:palm") for prefix in ("right/", "left/"))
        fingers_right, fingers_left = right.xmat.reshape(3, 3)[:, 2], left.xmat.reshape(3, 3)[:, 2]
        # The fingers point along each palm's z axis: at each other, horizontally, across the gap.
        np.testing.assert_allclose(fingers_right, [0, -1, 0], atol=1e-4)
        np.testing.assert_allclose(fingers_left, [0, 1, 0], atol=1e-4)
        assert left.xpos[1] < right.xpos[1]
        assert model.body("goal").mocapid[0] == env.layout.goal_mocap

    @pytest.mark.parametrize("task", list(TASK_IDS))
    def test_ball_stays_on_the_palm_when_the_hands_hold_still(self, task):
        env = make_env(num_envs=2, task=task)
        actions = torch.zeros(2, env.action_dim)
        rollout = env.rollout(75, policy=lambda td: td.set("action", actions), break_when_any_done=False)
        assert not rollout["next", "terminated"].any()
        ball = env.ball_pose()[0]
        assert np.all(np.linalg.norm(ball[:, :2] - env.task.ball_start[:2], axis=1) < 0.05)

    def test_license_notice_travels_with_the_package(self):
        package = os.path.dirname(sg_torchrl.envs.hands.__file__)
        notice = open(os.path.join(package, "NOTICE")).read()
        assert "Apache" in notice and "Vikash Kumar" in notice
        assert filecmp.cmp(os.path.join(package, "LICENSE-gymnasium-robotics-assets.md"),
                           os.path.join(hand_assets_dir(), "LICENSE.md"), shallow=False)

    def test_missing_gymnasium_robotics_says_how_to_install_it(self, monkeypatch):
        monkeypatch.setitem(sys.modules, "gymnasium_robotics", None)
        with pytest.raises(ImportError, match="pip install gymnasium-robotics"):
            hand_assets_dir()


# ---------------------------------------------------------------------------- sizes and specs
class TestSpecs:
    @pytest.mark.parametrize("task", list(TASK_IDS))
    @pytest.mark.parametrize("safety", list(IDS))
    def test_sizes_are_the_papers(self, safety, task):
        env = make_env(safety, num_envs=2, task=task)
        observation, action = PAPER_SIZES[task]
        assert env.observation_spec["observation"].shape == (2, observation)
        assert env.action_spec.shape == (2, action)
        assert (env.action_spec.space.low == -1).all() and (env.action_spec.space.high == 1).all()
        assert env.max_episode_steps == 75

    def test_constraints_per_variant(self):
        assert make_env("SafeJoint").constraint_names == ("forefinger_abduction",)
        assert make_env("SafeFinger").constraint_names == ("forefinger_abduction", "forefinger_flexion")

    def test_observation_layout_tail(self):
        env = make_env(seed=3)
        obs = env.reset()["observation"][0].numpy().astype(np.float64)
        ball_pos, ball_quat = env.ball_pose()
        goal_pos, goal_quat = env.goal_pose()
        np.testing.assert_allclose(obs[374:377], ball_pos[0], atol=1e-6)
        np.testing.assert_allclose(obs[377:381], ball_quat[0], atol=1e-6)
        np.testing.assert_allclose(obs[387:390], goal_pos[0], atol=1e-6)
        np.testing.assert_allclose(obs[390:394], goal_quat[0], atol=1e-6)
        np.testing.assert_allclose(obs[394:398], quat_multiply(ball_quat[0], goal_quat[0] * [1, -1, -1, -1]), atol=1e-6)
        # Joint positions of each hand, scaled to [-1, 1] over their ranges.
        assert np.all(np.abs(obs[:24]) <= 1 + 1e-6) and np.all(np.abs(obs[187:211]) <= 1 + 1e-6)

    def test_catch_over_moves_the_hand_bases(self):
        env = make_env(task="CatchOver2Underarm", seed=4)
        for hand in env.layout.hands:
            assert len(hand.base_qpos) == 6 and len(hand.actuators) == 26 and len(hand.qpos) == 24
            assert hand.actuator_names[20:] == tuple(f"A_{name}" for name in ("ARTx", "ARTy", "ARTz", "ARRx", "ARRy", "ARRz"))
        # Push the right hand's base up (z translation of its mount is the forearm's axis): the base pose observed follows.
        action = torch.zeros(1, 52)
        action[0, 20:26] = torch.tensor([0.5, 0.0, 0.0, 0.0, 0.0, 0.3])
        for _ in range(30):
            obs = env.step(TensorDict({"action": action}, batch_size=[1]))["next", "observation"][0].numpy()
        base = env.physics.qpos()[0, env.layout.hands[0].base_qpos]
        np.testing.assert_allclose(obs[167:173], base, atol=1e-6)  # after the fingertip forces, before the actions
        np.testing.assert_allclose(obs[173:199], action[0, :26].numpy(), atol=1e-6)
        assert base[0] == pytest.approx(0.05, abs=0.01) and base[5] == pytest.approx(0.15, abs=0.02)
        np.testing.assert_allclose(env.physics.qpos()[0, env.layout.hands[1].base_qpos], 0, atol=0.02)

    def test_bad_options_fail_clearly(self):
        with pytest.raises(ValueError, match="cost_source"):
            make_env(cost_source="torques")
        with pytest.raises(ValueError, match="SafeFinger"):
            ShadowHandEnv(safety="SafePalm")
        with pytest.raises(ValueError, match="CatchOver2Underarm"):
            ShadowHandEnv(task="HandUnder")


# ---------------------------------------------------------------------------- costs
class TestJointMapping:
    def test_paper_joints_are_the_forefinger_abduction_and_flexion_joints(self):
        env = make_env()
        model = env.physics.model
        for hand in env.layout.hands:
            ranges = {name: (hand.joint_low[i], hand.joint_high[i]) for i, name in enumerate(hand.joint_names)}
            np.testing.assert_allclose(ranges[PAPER_JOINTS[4]], (-20 * DEG, 20 * DEG), atol=1e-3)  # abduction
            for joint in (3, 2):  # flexion, 0 to 90 degrees
                np.testing.assert_allclose(ranges[PAPER_JOINTS[joint]], (0, 90 * DEG), atol=1e-3)
            abduction = model.joint(f"{hand.prefix}robot0:{PAPER_JOINTS[4]}")
            assert abs(model.jnt_axis[abduction.id][1]) == 1  # sideways, unlike the flexion joints (x axis)


ABDUCTION_CASES = [(0.0, 0), (9.9, 0), (-9.9, 0), (10.1, 1), (-10.1, 1), (19.0, 1)]
FLEXION_CASES = [(45.0, 0), (22.6, 0), (67.4, 0), (22.4, 1), (67.6, 1), (5.0, 1), (85.0, 1)]


class TestJointCost:
    """cost_source="joints": the measured angles of the named joints decide, exactly at the range edges."""

    @pytest.mark.parametrize("hand", [0, 1])
    @pytest.mark.parametrize("degrees,expected", ABDUCTION_CASES)
    @pytest.mark.parametrize("safety", list(IDS))
    def test_abduction(self, safety, degrees, expected, hand):
        env = make_env(safety, cost_mode="raw")
        place(env, 0, {PAPER_JOINTS[4]: degrees * DEG}, hand=hand)
        costs = env._compute_cost()
        assert costs["forefinger_abduction"][0] == expected
        if safety == "SafeFinger":
            assert costs["forefinger_flexion"][0] == 0

    @pytest.mark.parametrize("hand", [0, 1])
    @pytest.mark.parametrize("joint", [3, 2])
    @pytest.mark.parametrize("degrees,expected", FLEXION_CASES)
    def test_flexion_costs_in_safe_finger_only(self, joint, degrees, expected, hand):
        angles = {PAPER_JOINTS[joint]: degrees * DEG}
        finger, plain = make_env("SafeFinger", cost_mode="raw"), make_env("SafeJoint", cost_mode="raw")
        for env in (finger, plain):
            place(env, 0, angles, hand=hand)
        assert finger._compute_cost() == {"forefinger_abduction": [0], "forefinger_flexion": [expected]}
        assert plain._compute_cost() == {"forefinger_abduction": [0]}

    def test_raw_counts_every_violating_joint_of_both_hands(self):
        env = make_env("SafeFinger", cost_mode="raw")
        bad = {PAPER_JOINTS[4]: 15 * DEG, PAPER_JOINTS[3]: 80 * DEG, PAPER_JOINTS[2]: 10 * DEG}
        place(env, 0, bad, hand=0)
        costs = env._compute_cost()
        assert (costs["forefinger_abduction"][0], costs["forefinger_flexion"][0]) == (1, 2)
        place(env, 0, bad, hand=1)
        costs = env._compute_cost()
        assert (costs["forefinger_abduction"][0], costs["forefinger_flexion"][0]) == (1, 2)


class TestActionCost:
    """cost_source="actions" (the original code): the normalised actions of the joints' actuators, range +-0.5."""

    def step_with(self, env: ShadowHandEnv, entries: dict[int, float], action_dim: int = 40) -> TensorDict:
        env.reset()
        action = torch.zeros(1, action_dim)
        for index, value in entries.items():
            action[0, index] = value
        return env.step(TensorDict({"action": action}, batch_size=[1]))["next"]

    @pytest.mark.parametrize("task", list(TASK_IDS))
    @pytest.mark.parametrize("safety", list(IDS))
    @pytest.mark.parametrize("value,expected", [(0.0, 0), (0.49, 0), (-0.49, 0), (0.51, 1), (-0.51, 1), (1.0, 1)])
    def test_abduction_action(self, safety, value, expected, task):
        env = make_env(safety, cost_source="actions", task=task)
        per_hand = env.action_dim // 2
        for hand in env.layout.hands:
            index = per_hand * env.layout.hands.index(hand) + hand.actuator_index(PAPER_JOINTS[4])
            out = self.step_with(env, {index: value}, env.action_dim)
            assert out["cost_info", "forefinger_abduction"].item() == expected
            assert out["cost"].item() == expected

    @pytest.mark.parametrize("joint", [3, 2])
    @pytest.mark.parametrize("value,expected", [(0.0, 0), (0.49, 0), (-0.49, 0), (0.51, 1), (-0.51, 1), (-1.0, 1)])
    def test_flexion_action(self, joint, value, expected):
        finger, plain = make_env("SafeFinger", cost_source="actions"), make_env("SafeJoint", cost_source="actions")
        hand = finger.layout.hands[1]
        index = 20 + hand.actuator_index(PAPER_JOINTS[joint])
        assert self.step_with(finger, {index: value})["cost_info", "forefinger_flexion"].item() == expected
        assert self.step_with(plain, {index: value})["cost"].item() == 0

    def test_actuators_of_the_paper_joints(self):
        hand = make_env().layout.hands[0]
        assert [hand.actuator_names[hand.actuator_index(PAPER_JOINTS[j])] for j in (4, 3, 2)] == ["A_FFJ3", "A_FFJ2", "A_FFJ1"]


# ---------------------------------------------------------------------------- reward and termination
class TestReward:
    def test_rotation_distance_is_the_angle_between_orientations(self):
        goal = axis_angle([1, 2, 3], 0.7)
        for angle in (0.0, 0.3, 1.5, 3.0):
            ball = quat_multiply(axis_angle([0, 1, 1], angle), goal)
            assert rotation_distance(ball, goal) == pytest.approx(angle, abs=1e-9)

    @pytest.mark.parametrize("offset,angle", [((0, 0, 0), 0.0), ((0.1, 0, 0), 0.0), ((0, 0.05, 0.02), 0.8), ((0, 0, 0), 2.5)])
    def test_reward_at_known_poses(self, offset, angle):
        env = make_env(seed=1)
        goal_pos, goal_quat = (array[0].copy() for array in env.goal_pose())
        ball_quat = quat_multiply(axis_angle([1, 0, 0], angle), goal_quat)
        place(env, 0, ball_pos=goal_pos + offset, ball_quat=ball_quat)
        expected = np.exp(-0.2 * (20.0 * np.linalg.norm(offset) + angle))
        assert env._compute_reward(np.zeros((1, 40)))[0] == pytest.approx(expected, rel=1e-9)

    def test_reward_scale_option(self):
        env = make_env(distance_scale=5.0)
        goal_pos, goal_quat = (array[0].copy() for array in env.goal_pose())
        place(env, 0, ball_pos=goal_pos + (0.2, 0, 0), ball_quat=goal_quat)
        assert env._compute_reward(np.zeros((1, 40)))[0] == pytest.approx(np.exp(-0.2 * 5.0 * 0.2))

    def test_ball_falling_terminates(self):
        env = make_env(num_envs=2)
        env.reset()
        place(env, 1, ball_pos=(0.5, -0.5, 0.22))  # beside the hands, 2 cm above the fall height: it drops
        flags, heights = [], []
        for _ in range(10):
            out = env.step(TensorDict({"action": torch.zeros(2, 40)}, batch_size=[2]))["next"]
            flags.append(out["terminated"].squeeze(-1).tolist())
            heights.append(env.ball_pose()[0][1, 2])
        assert all(not first for first, _ in flags)  # the ball on the palm stays
        falling = [second for _, second in flags]
        assert falling == [height < env.fall_height for height in heights]
        assert not falling[0] and falling[-1]


# ---------------------------------------------------------------------------- seeding and long runs
class TestSeeding:
    @pytest.mark.parametrize("task", list(TASK_IDS))
    @pytest.mark.parametrize("safety", list(IDS))
    def test_sim0_same_for_one_and_four_sims(self, safety, task):
        # Short episodes, so that simulator 0 is truncated (and auto-reset) before the ball can fall.
        small, large = (make_env(safety, num_envs=n, seed=7, task=task, max_episode_steps=15) for n in (1, 4))
        assert_sim0_same_for_any_batch(small, large, steps=50)

    def test_different_seeds_draw_different_goals(self):
        a, b = make_env(seed=0), make_env(seed=1)
        a.reset(), b.reset()
        assert not np.allclose(a.goal_pose()[1], b.goal_pose()[1])

    def test_snapshot_replays(self):
        env = make_env(num_envs=2, seed=2)
        env.reset()
        actions = torch.rand((6, 2, 40), generator=torch.Generator().manual_seed(0)) * 2 - 1
        env.rollout(3, break_when_any_done=False)
        state = env.sim_state()
        first = [env.step(TensorDict({"action": a}, batch_size=[2]))["next", "observation"] for a in actions]
        env.load_sim_state(state)
        again = [env.step(TensorDict({"action": a}, batch_size=[2]))["next", "observation"] for a in actions]
        for x, y in zip(first, again):
            torch.testing.assert_close(x, y, rtol=0, atol=0)


@pytest.mark.parametrize("task,steps", [("HandOver", 2500), ("CatchOver2Underarm", 600)])
def test_random_steps_stay_finite(task, steps):
    """4 simulators x ``steps`` random steps (HandOver: 10,000 in all, 33 episodes per simulator; CatchOver2Underarm,
    slower: 2,400): finite observations, rewards in (0, 1], costs in {0, 1}, no simulator diverged."""
    env = make_env("SafeFinger", num_envs=4, seed=0, task=task)
    rollout = env.rollout(steps, break_when_any_done=False)
    nxt = rollout["next"]
    assert torch.isfinite(nxt["observation"]).all()
    assert ((nxt["reward"] > 0) & (nxt["reward"] <= 1)).all()
    assert set(nxt["cost"].unique().tolist()) <= {0.0, 1.0}
    assert nxt["done"].sum() >= 4 * (steps // 75)
    assert env.physics_errors == 0


# ---------------------------------------------------------------------------- multi-agent form
class TestMultiAgent:
    """``MultiAgent...`` ids: one agent per hand, TorchRL's MARL layout, each agent paying for its own forefinger."""

    def make(self, task: str = "HandOver", safety: str = "SafeFinger", **options):
        return sg_torchrl.make("MultiAgent" + TASK_IDS[task][safety], **options)

    @pytest.mark.parametrize("task", list(TASK_IDS))
    def test_same_world_as_the_single_agent_env(self, task):
        """The group action, flattened, is the single-agent action; the state is the single-agent observation."""
        single, multi = make_env(num_envs=2, seed=5, task=task), self.make(task, num_envs=2, seed=5)
        per_hand = single.action_dim // 2
        actions = torch.rand((4, 2, 2 * per_hand), generator=torch.Generator().manual_seed(1)) * 2 - 1
        single.reset(), multi.reset()
        for action in actions:
            a = single.step(TensorDict({"action": action}, batch_size=[2]))["next"]
            b = multi.step(TensorDict({("agents", "action"): action.reshape(2, 2, per_hand)}, batch_size=[2]))["next"]
            torch.testing.assert_close(b["state"], a["observation"], rtol=0, atol=0)
            torch.testing.assert_close(b["agents", "reward"], a["reward"].unsqueeze(-2).expand(2, 2, 1), rtol=0, atol=0)
        hand = single.hand_observation_dim
        for agent in range(2):
            own = b["state"][:, agent * hand:(agent + 1) * hand]
            torch.testing.assert_close(b["agents", "observation"][:, agent], torch.cat((own, b["state"][:, -24:]), dim=-1))

    @pytest.mark.parametrize("hand", [0, 1])
    def test_each_agent_pays_for_its_own_hand(self, hand):
        env = self.make(num_envs=1, seed=0)
        env.reset()
        # Hand ``hand`` bends its forefinger past 67.5 degrees (knuckle flexion action 0.9 > 0.5): measured after 20 steps.
        action = torch.zeros(1, 2, 20)
        action[0, hand, env.layout.hands[hand].actuator_index(PAPER_JOINTS[3])] = 0.9
        for _ in range(20):
            out = env.step(TensorDict({("agents", "action"): action}, batch_size=[1]))["next"]
        other = 1 - hand
        assert out["agents", "cost_info", "forefinger_flexion"][0, hand].item() == 1
        assert out["agents", "cost_info", "forefinger_flexion"][0, other].item() == 0
        assert out["agents", "cost"][0, :, 0].tolist() == [1.0 if a == hand else 0.0 for a in range(2)]
        assert out["cost"].item() == 1 and out["cost_info", "forefinger_flexion"].item() == 1

    def test_pettingzoo_facade(self):
        import sg_torchrl.pettingzoo as pz

        env = pz.make("MultiAgentShadowHandOverSafeJoint-v0")
        observations, _ = env.reset(seed=0)
        assert {agent: obs.shape for agent, obs in observations.items()} == {"agent_0": (211,), "agent_1": (211,)}
        out = env.step({agent: env.action_space(agent).sample() for agent in env.agents})
        assert len(out) == 6 and all(set(part) == {"agent_0", "agent_1"} for part in out)


# ---------------------------------------------------------------------------- rendering
@pytest.mark.parametrize("env_id", ["ShadowHandOverSafeJoint-v0", "MultiAgentShadowHandCatchOver2UnderarmSafeFinger-v0"])
def test_render_shows_both_hands_and_the_ball(backend, env_id):
    env = sg_torchrl.make(env_id, num_envs=2, seed=0)
    env.reset()
    frame = env.render(0, width=120, height=90)
    assert frame.shape == (90, 120, 3) and frame.dtype == np.uint8
    assert frame.std() > 10 and len(np.unique(frame.reshape(-1, 3), axis=0)) > 20  # a picture, not a blank
    assert np.array_equal(env.render(0, 120, 90), frame)  # rendering only reads the state
    # Lift simulator 0's ball well above the hands: the picture changes, simulator 1's does not.
    other = env.render(1, 120, 90)
    start = env.layout.ball_qpos
    env.physics.datas[0].qpos[start + 2] += 0.15
    mujoco.mj_forward(env.physics.model, env.physics.datas[0])
    assert not np.array_equal(env.render(0, 120, 90), frame)
    assert np.array_equal(env.render(1, 120, 90), other)
    env.close()
    with pytest.raises(RuntimeError, match="after close"):
        env.render(0)


# ---------------------------------------------------------------------------- training
class TestTraining:
    """``sg-train`` on the two-hand ids: the ``hands`` preset, and both agent layouts end to end."""

    def test_hands_preset_follows_safepos_isaac_gym_config_in_whole_episodes(self):
        from sg_torchrl.train.command_line import parse_args

        cfg = parse_args(["--preset", "hands"])
        assert (cfg.algo, cfg.env_id) == ("ppo_lag", "ShadowHandOverSafeJoint-v0")
        # SafePO's Isaac Gym override: gamma 0.96, target KL 0.016, 8 passes of 4 minibatches, clip 1.0, no critic L2.
        assert (cfg.gamma, cfg.target_kl, cfg.update_iters, cfg.max_grad_norm, cfg.critic_l2) == (0.96, 0.016, 8, 1.0, 0.0)
        assert cfg.steps_per_epoch == 4 * cfg.minibatch_size
        assert cfg.steps_per_epoch % (cfg.num_envs * 75) == 0  # every simulator ends its episodes within the epoch
        assert cfg.total_steps % cfg.steps_per_epoch == 0
        assert cfg.env_options == {"physics_threads": 2}

    @pytest.mark.parametrize("algo, env_id", [("ppo_lag", "ShadowHandOverSafeJoint-v0"),
                                              ("mappo_lag", "MultiAgentShadowHandOverSafeFinger-v0")])
    def test_sg_train_runs_end_to_end(self, tmp_path, algo, env_id):
        import csv

        from sg_torchrl.train import main

        code = main(["--preset", "hands", "--algo", algo, "--env-id", env_id, "--num-envs", "4",
                     "--steps-per-epoch", "300", "--minibatch-size", "150", "--total-steps", "600",
                     "--hidden-sizes", "32", "32", "--eval-episodes", "1", "--wandb", "disabled",
                     "--progress", "false", "--output-dir", str(tmp_path), "--run-name", "hands"])
        assert code == 0
        with open(tmp_path / "hands" / "progress.csv") as handle:
            rows = [row for row in csv.DictReader(handle) if row["Train/Epoch"]]
        assert len(rows) == 2
        for row in rows:
            # 75-step episodes unless the ball falls first, which random actions make it do now and then: the
            # mean length is the time limit or a little under it.
            assert 60.0 < float(row["Metrics/EpLen"]) <= 75.0
            assert 0.0 <= float(row["Metrics/EpCost"]) <= 2 * 75  # both hands' forefingers, per step
            assert 0.0 < float(row["Metrics/EpRet"]) < 75.0  # exp(-...) <= 1 per step
