"""The env registry: every registered id builds a valid batched TorchRL env; unknown ids fail helpfully."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import check_env_specs

import sg_torchrl
from sg_torchrl.envs import UnknownEnvError, registry_entry
from sg_torchrl.envs.registry import env_options

torch.set_num_threads(1)

# The Vision ids (one per navigation id) render images (an OpenGL backend, slower steps): tests/test_vision.py covers them
# (specs, rollouts, sizes per robot); here every other id.
VISION_IDS = sg_torchrl.list_envs(family="vision")
ALL_IDS = [env_id for env_id in sg_torchrl.list_envs() if env_id not in VISION_IDS]

# reference/safety_gymnasium_semantics.md, section 10: (observation size, action size) per robot.
REFERENCE_SIZES = {
    "Ant": (27, 8),
    "HalfCheetah": (17, 6),
    "Hopper": (11, 3),
    "Humanoid": (376, 17),
    "Swimmer": (8, 2),
    "Walker2d": (17, 6),
}
# Navigation sizes depend on the task level (reference section 2): per id.
REFERENCE_SIZES_BY_ID = {
    "SafetyPointGoal0-v0": (28, 2),
    "SafetyPointGoal1-v0": (60, 2),
    "SafetyPointGoal2-v0": (60, 2),
    # Button0: buttons_lidar, goal_lidar; Button1/2: + hazards, gremlins. Push0: goal, push_box; Push1/2: + hazards, pillars.
    "SafetyPointButton0-v0": (44, 2),
    "SafetyPointButton1-v0": (76, 2),
    "SafetyPointButton2-v0": (76, 2),
    "SafetyPointPush0-v0": (44, 2),
    "SafetyPointPush1-v0": (76, 2),
    "SafetyPointPush2-v0": (76, 2),
    # Car: 24 robot values (12 sensors + ballangvel_rear 3 + ballquat_rear 9); Circle: circle_lidar only; Run: none.
    "SafetyCarGoal0-v0": (40, 2),
    "SafetyCarGoal1-v0": (72, 2),
    "SafetyCarGoal2-v0": (72, 2),
    "SafetyCarButton0-v0": (56, 2),
    "SafetyCarButton1-v0": (88, 2),
    "SafetyCarButton2-v0": (88, 2),
    "SafetyCarPush0-v0": (56, 2),
    "SafetyCarPush1-v0": (88, 2),
    "SafetyCarPush2-v0": (88, 2),
    "SafetyPointCircle0-v0": (28, 2),
    "SafetyPointCircle1-v0": (28, 2),
    "SafetyPointCircle2-v0": (28, 2),
    "SafetyCarCircle0-v0": (40, 2),
    "SafetyCarCircle1-v0": (40, 2),
    "SafetyCarCircle2-v0": (40, 2),
    "SafetyPointRun0-v0": (12, 2),
    "SafetyCarRun0-v0": (24, 2),
    # Racecar 12 robot values (the fixed sensors only), Doggo 56 (12 + 8 touch + 12 hinge velocities + 12 x (sin, cos)),
    # Ant 40 (12 + 8 hinge velocities + height 1 + agent_qvel 3 + 8 x (sin, cos)); reference section 2.
    "SafetyRacecarGoal0-v0": (28, 2),
    "SafetyRacecarGoal1-v0": (60, 2),
    "SafetyRacecarGoal2-v0": (60, 2),
    "SafetyRacecarButton0-v0": (44, 2),
    "SafetyRacecarButton1-v0": (76, 2),
    "SafetyRacecarButton2-v0": (76, 2),
    "SafetyRacecarPush0-v0": (44, 2),
    "SafetyRacecarPush1-v0": (76, 2),
    "SafetyRacecarPush2-v0": (76, 2),
    "SafetyRacecarCircle0-v0": (28, 2),
    "SafetyRacecarCircle1-v0": (28, 2),
    "SafetyRacecarCircle2-v0": (28, 2),
    "SafetyRacecarRun0-v0": (12, 2),
    "SafetyDoggoGoal0-v0": (72, 12),
    "SafetyDoggoGoal1-v0": (104, 12),
    "SafetyDoggoGoal2-v0": (104, 12),
    "SafetyDoggoButton0-v0": (88, 12),
    "SafetyDoggoButton1-v0": (120, 12),
    "SafetyDoggoButton2-v0": (120, 12),
    "SafetyDoggoPush0-v0": (88, 12),
    "SafetyDoggoPush1-v0": (120, 12),
    "SafetyDoggoPush2-v0": (120, 12),
    "SafetyDoggoCircle0-v0": (72, 12),
    "SafetyDoggoCircle1-v0": (72, 12),
    "SafetyDoggoCircle2-v0": (72, 12),
    "SafetyDoggoRun0-v0": (56, 12),
    "SafetyAntGoal0-v0": (56, 8),
    "SafetyAntGoal1-v0": (88, 8),
    "SafetyAntGoal2-v0": (88, 8),
    "SafetyAntButton0-v0": (72, 8),
    "SafetyAntButton1-v0": (104, 8),
    "SafetyAntButton2-v0": (104, 8),
    "SafetyAntPush0-v0": (72, 8),
    "SafetyAntPush1-v0": (104, 8),
    "SafetyAntPush2-v0": (104, 8),
    "SafetyAntCircle0-v0": (56, 8),
    "SafetyAntCircle1-v0": (56, 8),
    "SafetyAntCircle2-v0": (56, 8),
    "SafetyAntRun0-v0": (40, 8),
}
# Fading ids observe exactly what the Goal id of the same robot and level does (only what is drawn differs).
REFERENCE_SIZES_BY_ID.update({
    env_id.replace("Goal", fading): size
    for env_id, size in list(REFERENCE_SIZES_BY_ID.items()) if "Goal" in env_id for fading in ("FadingEasy", "FadingHard")
})
# Race: the robot's sensors (Run0's size), then goal_lidar, then hazards_lidar at levels 1-2 (the scenery is not observed).
REFERENCE_SIZES_BY_ID.update({
    f"Safety{robot}Race{level}-v0": (REFERENCE_SIZES_BY_ID[f"Safety{robot}Run0-v0"][0] + (16 if level == 0 else 32),
                                     REFERENCE_SIZES_BY_ID[f"Safety{robot}Run0-v0"][1])
    for robot in ("Point", "Car", "Racecar", "Doggo", "Ant") for level in range(3)
})

# Building and FormulaOne (the paper's scenes, not in the reference; composition in tasks/building.py,
# tasks/formula_one.py): robot sensors, then 16 lidar bins per observed group (levels 0, 1, 2).
_SENSORS_AND_ACTIONS = {"Point": (12, 2), "Car": (24, 2), "Racecar": (12, 2), "Doggo": (56, 12), "Ant": (40, 8)}
_LIDAR_GROUPS = {"BuildingGoal": (1, 3, 3), "BuildingButton": (2, 4, 4), "BuildingPush": (2, 4, 4), "FormulaOne": (1, 3, 3)}
REFERENCE_SIZES_BY_ID.update({
    f"Safety{robot}{task}{level}-v0": (sensors + 16 * groups, actions)
    for robot, (sensors, actions) in _SENSORS_AND_ACTIONS.items()
    for task, per_level in _LIDAR_GROUPS.items()
    for level, groups in enumerate(per_level)
})

# Dexterous hands (the paper's section 4.4; sg_torchrl.envs.hands): ShadowHandOver 398 / 40, CatchOver2Underarm 422 / 52.
REFERENCE_SIZES_BY_ID.update({
    f"ShadowHand{task}{safety}-v0": size
    for task, size in (("Over", (398, 40)), ("CatchOver2Underarm", (422, 52))) for safety in ("SafeJoint", "SafeFinger")
})

# Multi-agent velocity (reference section 10): per-agent (observation, action) sizes, state size, threshold.
MULTI_AGENT_SIZES = {
    "Safety2x4AntVelocity-v0": ([(21, 4), (21, 4)], 27, 2.522),
    "Safety4x2AntVelocity-v0": ([(18, 2)] * 4, 27, 2.418),
    "Safety2x3HalfCheetahVelocity-v0": ([(12, 3), (12, 3)], 17, 3.227),
    "Safety6x1HalfCheetahVelocity-v0": ([(9, 1), (9, 1), (8, 1), (9, 1), (9, 1), (8, 1)], 17, 2.932),
    "Safety3x1HopperVelocity-v0": ([(8, 1), (9, 1), (8, 1)], 11, 0.9613),
    "Safety9|8HumanoidVelocity-v0": ([(248, 9), (176, 8)], 376, 0.58),
    "Safety2x1SwimmerVelocity-v0": ([(6, 1), (6, 1)], 8, 0.04891),
    "Safety2x3Walker2dVelocity-v0": ([(11, 3), (11, 3)], 17, 1.641),
}


# Multi-agent navigation (Safety-Gymnasium's MultiGoal): per-agent (observation, action) sizes and the state size.
# Every agent observes the joint vector: both robots' sensors (Point 12, Ant 40 each), then each robot's lidars
# (16 bins per object: goal_red, goal_blue; levels 1-2 add hazards and vases).
MULTI_GOAL_SIZES = {
    "SafetyPointMultiGoal0-v0": ([(88, 2)] * 2, 88),
    "SafetyPointMultiGoal1-v0": ([(152, 2)] * 2, 152),
    "SafetyPointMultiGoal2-v0": ([(152, 2)] * 2, 152),
    "SafetyAntMultiGoal0-v0": ([(144, 8)] * 2, 144),
    "SafetyAntMultiGoal1-v0": ([(208, 8)] * 2, 208),
    "SafetyAntMultiGoal2-v0": ([(208, 8)] * 2, 208),
}


def make_env(env_id: str, num_envs: int = 3, seed: int = 0, **options):
    return sg_torchrl.make(env_id, num_envs=num_envs, seed=seed, **options)


class TestListEnvs:
    def test_velocity_family_has_twelve_ids(self):
        ids = sg_torchrl.list_envs(family="velocity")
        assert len(ids) == 12
        assert ids == sorted(ids)
        expected = {f"Safety{robot}Velocity-v{v}" for robot in REFERENCE_SIZES for v in (0, 1)}
        assert set(ids) == expected

    def test_multi_agent_velocity_family_has_eight_ids(self):
        ids = sg_torchrl.list_envs(family="multi_agent_velocity")
        assert set(ids) == set(MULTI_AGENT_SIZES)
        assert all(registry_entry(i).multi_agent for i in ids)
        assert not any(registry_entry(i).multi_agent for i in sg_torchrl.list_envs(family="velocity"))

    def test_multi_agent_navigation_family_has_six_ids(self):
        ids = sg_torchrl.list_envs(family="multi_agent_navigation")
        assert set(ids) == set(MULTI_GOAL_SIZES)
        assert all(registry_entry(i).multi_agent and registry_entry(i).task == "MultiGoal" for i in ids)
        assert not any("MultiGoal" in i for i in sg_torchrl.list_envs(family="navigation"))

    def test_filter_by_robot(self):
        # "Ant" names a velocity, a navigation and a multi-agent robot: the family tells them apart.
        velocity = ["SafetyAntVelocity-v0", "SafetyAntVelocity-v1"]
        assert sg_torchrl.list_envs(family="velocity", robot="Ant") == velocity
        navigation = sg_torchrl.list_envs(family="navigation", robot="Ant")
        assert len(navigation) == 34 and "SafetyAntGoal1-v0" in navigation  # Goal, Button, Push, Circle, Fading*, Race, Building*, FormulaOne 0-2; Run0
        multi_agent = sg_torchrl.list_envs(family="multi_agent_velocity", robot="Ant")
        assert multi_agent == ["Safety2x4AntVelocity-v0", "Safety4x2AntVelocity-v0"]
        multi_goal = sg_torchrl.list_envs(family="multi_agent_navigation", robot="Ant")
        assert multi_goal == [f"SafetyAntMultiGoal{level}-v0" for level in range(3)]
        vision = sg_torchrl.list_envs(family="vision", robot="Ant")
        assert vision == sorted(i.replace("-v0", "Vision-v0") for i in navigation)  # one Vision id per navigation id
        assert sg_torchrl.list_envs(robot="Ant") == sorted(velocity + navigation + vision + multi_agent + multi_goal)

    def test_unknown_family_is_empty(self):
        assert sg_torchrl.list_envs(family="no-such-family") == []

    def test_entries_carry_metadata(self):
        entry = registry_entry("SafetyHopperVelocity-v1")
        assert (entry.family, entry.robot, entry.task, entry.max_episode_steps) == ("velocity", "Hopper", "Velocity", 1000)


class TestUnknownId:
    def test_suggests_closest_id(self):
        with pytest.raises(UnknownEnvError) as info:
            sg_torchrl.make("SafetyHalfCheetahVelocity-v2")
        message = str(info.value)
        assert "'SafetyHalfCheetahVelocity-v2'" in message
        assert "Did you mean 'SafetyHalfCheetahVelocity-v1'" in message

    def test_is_a_key_error(self):
        # Code that catches KeyError for missing ids keeps working.
        with pytest.raises(KeyError):
            sg_torchrl.make("SafetyNoSuchThing-v0")

    def test_no_suggestion_for_nonsense(self):
        with pytest.raises(UnknownEnvError) as info:
            sg_torchrl.make("xyz")
        assert "Did you mean" not in str(info.value)
        assert "list_envs()" in str(info.value)


class TestMakeOptions:
    def test_num_envs_zero(self):
        with pytest.raises(ValueError, match="num_envs"):
            make_env("SafetyHalfCheetahVelocity-v1", num_envs=0)

    def test_bogus_cost_mode(self):
        with pytest.raises(ValueError, match="cost_mode"):
            make_env("SafetyHalfCheetahVelocity-v1", cost_mode="bogus")

    def test_options_override_registry_defaults(self):
        env = make_env("SafetyHalfCheetahVelocity-v1", num_envs=1, max_episode_steps=17)
        assert env.max_episode_steps == 17
        assert make_env("SafetyHalfCheetahVelocity-v1", num_envs=1).max_episode_steps == 1000

    def test_unknown_option_names_it_and_lists_the_accepted_ones(self):
        with pytest.raises(TypeError, match=r"unknown option\(s\) 'lidar'.*velocity_threshold"):
            make_env("Safety2x3HalfCheetahVelocity-v0", lidar="natural")

    @pytest.mark.parametrize(
        "env_id, expected",
        [
            ("SafetyHalfCheetahVelocity-v1", {"cost_mode", "max_episode_steps", "velocity_threshold"}),
            ("SafetyPointGoal1-v0", {"cost_mode", "max_episode_steps", "lidar", "compass", "obs_mode", "image_size"}),
            ("SafetyPointGoal1Vision-v0", {"cost_mode", "max_episode_steps", "lidar", "compass", "obs_mode",
                                           "image_size"}),
            ("Safety2x3HalfCheetahVelocity-v0", {"cost_mode", "max_episode_steps", "velocity_threshold"}),
        ],
    )
    def test_env_options_lists_the_constructor_keywords_the_entry_leaves_open(self, env_id, expected):
        options = set(env_options(env_id))
        assert expected <= options
        assert not options & {"self", "num_envs", "device", "seed", "robot", "task", "level", "version"}


@pytest.mark.parametrize("env_id", ALL_IDS)
class TestEveryId:
    def test_check_env_specs(self, env_id):
        env = make_env(env_id)
        check_env_specs(env, seed=0)
        assert env.batch_size == torch.Size([3])

    def test_rollout(self, env_id):
        env = make_env(env_id)
        steps = 20
        rollout = env.rollout(steps, break_when_any_done=False)
        assert rollout.batch_size == torch.Size([3, steps])
        nxt = rollout["next"]
        multi_agent = registry_entry(env_id).multi_agent
        # Multi-agent envs: TorchRL's group layout (reward, observation per agent; state, cost at the root too).
        reward_key, observation_key = ("reward", "observation")
        if multi_agent:
            reward_key, observation_key = ("agents", "reward"), ("agents", "observation")
        assert env.reward_key == reward_key
        for key in (reward_key, "cost"):
            assert nxt[key].shape[:2] == (3, steps) and nxt[key].shape[-1] == 1, key
            assert nxt[key].dtype == torch.float32, key
            assert torch.isfinite(nxt[key]).all(), key
        assert torch.isfinite(nxt[observation_key]).all()
        assert nxt[observation_key].dtype == torch.float32
        if multi_agent:
            agents = env.num_agents
            for key in ("reward", "cost", "done", "terminated", "truncated"):
                assert nxt["agents", key].shape == (3, steps, agents, 1), key
            # Every agent shares the episode flags.
            for key in ("done", "terminated", "truncated"):
                assert (nxt["agents", key] == nxt[key].unsqueeze(-2)).all(), key
            if registry_entry(env_id).family == "multi_agent_velocity":
                # One robot: every agent shares the team reward and the cost.
                assert (nxt["agents", "cost"] == nxt["cost"].unsqueeze(-2)).all()
                assert (nxt["agents", "reward"] == nxt["agents", "reward"][..., :1, :]).all()
            else:
                # Several robots: each agent pays its own cost; the team's is 1 when some agent paid.
                torch.testing.assert_close(nxt["cost"], nxt["agents", "cost"].amax(dim=-2))
            assert torch.isfinite(nxt["state"]).all()
        assert set(nxt["cost_info"].keys()) == set(env.constraint_names)
        for name in env.constraint_names:
            assert nxt["cost_info", name].shape == (3, steps, 1), name
        if registry_entry(env_id).family == "velocity":
            assert env.constraint_names == ("velocity",)
        # Indicator costs: the total is 1 exactly when some constraint fired, in {0, 1}.
        fired = torch.zeros_like(nxt["cost"])
        for name in env.constraint_names:
            fired = torch.maximum(fired, nxt["cost_info", name])
        torch.testing.assert_close(nxt["cost"], fired)
        assert set(nxt["cost"].unique().tolist()) <= {0.0, 1.0}

    def test_sizes_match_reference(self, env_id):
        env = make_env(env_id, num_envs=1)
        if registry_entry(env_id).family == "multi_agent_navigation":
            agents, state_dim = MULTI_GOAL_SIZES[env_id]
            assert list(zip(env.observation_sizes, env.action_sizes)) == agents
            assert env.observation_spec["agents", "observation"].shape == (1, len(agents), agents[0][0])
            assert env.full_action_spec[env.action_key].shape == (1, len(agents), agents[0][1])
            assert env.observation_spec["state"].shape == (1, state_dim)
            return
        if registry_entry(env_id).family == "multi_agent_dexhands":
            # One agent per hand: its hand's block of the single-agent observation plus the ball and goal (24 values).
            state_dim, actions = REFERENCE_SIZES_BY_ID[env_id.removeprefix("MultiAgent")]
            agent = ((state_dim - 24) // 2 + 24, actions // 2)
            assert list(zip(env.observation_sizes, env.action_sizes)) == [agent, agent]
            assert env.observation_spec["agents", "observation"].shape == (1, 2, agent[0])
            assert env.full_action_spec[env.action_key].shape == (1, 2, agent[1])
            assert env.observation_spec["state"].shape == (1, state_dim)
            return
        if registry_entry(env_id).multi_agent:
            agents, state_dim, threshold = MULTI_AGENT_SIZES[env_id]
            assert list(zip(env.observation_sizes, env.action_sizes)) == agents
            assert env.observation_spec["agents", "observation"].shape == (1, len(agents), max(o for o, _ in agents))
            assert env.full_action_spec[env.action_key].shape == (1, len(agents), max(a for _, a in agents))
            assert env.observation_spec["state"].shape == (1, state_dim)
            assert env.velocity_threshold == threshold
            return
        obs_size, act_size = REFERENCE_SIZES_BY_ID.get(env_id) or REFERENCE_SIZES[registry_entry(env_id).robot]
        assert env.observation_spec["observation"].shape == (1, obs_size)
        assert env.action_spec.shape == (1, act_size)
        assert env.observation_dim == obs_size and env.action_dim == act_size
