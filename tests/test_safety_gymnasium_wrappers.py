"""Every wrapper of sg_torchrl.safety_gymnasium.wrappers, used as the original's clients use them
(SafePO's single-env stack: SafeAutoResetWrapper, SafeRescaleAction, SafeNormalizeObservation,
SafeUnsqueeze; gymnasium wrappers through with_gymnasium_wrappers)."""

from __future__ import annotations

import functools

import gymnasium
import numpy as np
import pytest

import sg_torchrl.safety_gymnasium as safety_gymnasium
from sg_torchrl.safety_gymnasium.wrappers import (
    Gymnasium2SafetyGymnasium,
    SafeAutoResetWrapper,
    SafeNormalizeCost,
    SafeNormalizeObservation,
    SafeNormalizeReward,
    SafePassiveEnvChecker,
    SafeRescaleAction,
    SafetyGymnasium2Gymnasium,
    SafeTimeLimit,
    SafeUnsqueeze,
    with_gymnasium_wrappers,
)

VEL_ID = "SafetyHalfCheetahVelocity-v1"
NAV_ID = "SafetyPointGoal0-v0"


def bare(env_id: str = VEL_ID, **kwargs) -> gymnasium.Env:
    """The unwrapped 6-tuple env (what the wrappers are put around)."""
    return safety_gymnasium.make(env_id, disable_env_checker=True, **kwargs).unwrapped


def test_safepo_single_env_stack():
    # safepo.common.env.make_sa_mujoco_env with num_envs=1
    env = safety_gymnasium.make(VEL_ID, max_episode_steps=4, velocity_threshold=-1e9)
    env.reset(seed=0)
    obs_space, act_space = env.observation_space, env.action_space
    env = SafeUnsqueeze(SafeNormalizeObservation(SafeRescaleAction(SafeAutoResetWrapper(env), -1.0, 1.0)))
    obs, info = env.reset(seed=0)
    assert obs.shape == (1, obs_space.shape[0])
    for step in range(1, 9):
        obs, reward, cost, terminated, truncated, info = env.step(np.zeros(act_space.shape))
        assert obs.shape == (1, 17) and reward.shape == (1,) and cost.shape == (1,) and truncated.shape == (1,)
        assert cost[0] == 1.0
        if step % 4 == 0:  # autoreset: the final observation is normalised and unsqueezed
            assert truncated[0] and info["final_observation"].shape == (1, 17)
            assert info["original_final_observation"].shape == (1, 17)
            rows = [array if array is not None else np.zeros(17) for array in info["final_observation"]]
            assert np.asarray(rows).shape == (1, 17)  # how SafePO reads it
        else:
            assert not truncated[0]
    env.close()


def test_autoreset_resets_within_the_step_and_keeps_the_final_cost():
    env = SafeAutoResetWrapper(SafeTimeLimit(bare(velocity_threshold=-1e9), max_episode_steps=2))
    first, _ = env.reset(seed=3)
    reference = SafeTimeLimit(bare(velocity_threshold=-1e9), max_episode_steps=2)
    reference.reset(seed=3)
    action = np.full(6, 0.5)
    env.step(action), reference.step(action)
    obs, reward, cost, terminated, truncated, info = env.step(action)
    final = reference.step(action)
    assert truncated and cost == final[2] == 1.0 and reward == final[1]
    np.testing.assert_array_equal(info["final_observation"], final[0])
    assert info["final_info"] == final[5]
    assert not np.array_equal(obs, final[0])  # the new episode's first observation

    class Clashing(gymnasium.Wrapper):
        def reset(self, **kwargs):
            obs, info = self.env.reset(**kwargs)
            return obs, {"final_info": 1}

    clashing = SafeAutoResetWrapper(Clashing(SafeTimeLimit(bare(), max_episode_steps=1)))
    clashing.reset(seed=0)
    with pytest.raises(ValueError, match="final_info"):
        clashing.step(action)


def test_time_limit_truncates_and_reports_in_spec():
    env = SafeTimeLimit(bare(), max_episode_steps=3)
    assert isinstance(env, gymnasium.wrappers.TimeLimit) and env.spec.max_episode_steps == 3
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros(6))
    env.reset(seed=0)
    flags = [env.step(np.zeros(6))[4] for _ in range(3)]
    assert flags == [False, False, True]
    with pytest.raises(ValueError):
        SafeTimeLimit(bare(), max_episode_steps=0)


def test_passive_env_checker_checks_the_six_tuple():
    env = SafePassiveEnvChecker(bare())
    env.reset(seed=0)
    assert len(env.step(np.zeros(6))) == 6

    class FiveTuple(gymnasium.Wrapper):
        def step(self, action):
            return self.env.step(action)[:5]

    broken = SafePassiveEnvChecker(FiveTuple(bare()))
    broken.reset(seed=0)
    with pytest.raises(ValueError, match="the 6 elements .* got 5"):
        broken.step(np.zeros(6))


def test_conversions_and_gymnasium_wrappers():
    env = SafetyGymnasium2Gymnasium(bare(velocity_threshold=-1e9))
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(np.zeros(6))
    assert info["cost"] == 1.0
    back = Gymnasium2SafetyGymnasium(env)
    assert back.step(np.zeros(6))[2] == 1.0

    class NoCost(gymnasium.Wrapper):
        def step(self, action):
            obs, reward, terminated, truncated, info = self.env.step(action)
            info.pop("cost")
            return obs, reward, terminated, truncated, info

    lost = Gymnasium2SafetyGymnasium(NoCost(SafetyGymnasium2Gymnasium(bare())))
    lost.reset(seed=0)
    with pytest.raises(ValueError, match="cost"):
        lost.step(np.zeros(6))
    # gymnasium's own wrappers on a 6-tuple env
    wrapped = with_gymnasium_wrappers(
        bare(velocity_threshold=-1e9),
        gymnasium.wrappers.ClipAction,
        functools.partial(gymnasium.wrappers.TransformObservation, func=lambda o: o * 0.0,
                          observation_space=bare().observation_space),
    )
    wrapped.reset(seed=0)
    obs, reward, cost, terminated, truncated, info = wrapped.step(np.full(6, 5.0))
    assert cost == 1.0 and not obs.any()
    with pytest.raises(TypeError, match="not callable"):
        with_gymnasium_wrappers(bare(), "ClipAction")
    # the twin ids are gymnasium envs with the cost in info
    twin = gymnasium.make("SafetyPointGoal0Gymnasium-v0")
    twin.reset(seed=0)
    assert "cost" in twin.step(twin.action_space.sample())[4]


def test_rescale_action_maps_onto_the_bounds():
    inner = bare("SafetyHumanoidVelocity-v1")  # bounds [-0.4, 0.4]
    env = SafeRescaleAction(inner, -1.0, 1.0)
    assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, inner.action_space.shape, inner.action_space.dtype)
    np.testing.assert_allclose(env.action(np.ones(17)), inner.action_space.high, rtol=1e-6)
    np.testing.assert_allclose(env.action(np.zeros(17)), (inner.action_space.low + inner.action_space.high) / 2,
                               atol=1e-7)
    env.reset(seed=0)
    assert len(env.step(np.zeros(17))) == 6
    with pytest.raises(ValueError, match="below"):
        SafeRescaleAction(bare(), 1.0, -1.0)
    with pytest.raises(ValueError, match="shape"):
        SafeRescaleAction(bare(), np.zeros(3), 1.0)


def test_normalizers_scale_by_running_statistics():
    env = SafeNormalizeCost(SafeNormalizeReward(SafeNormalizeObservation(bare(velocity_threshold=-1e9)),
                                                gamma=0.9), gamma=0.9)
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)
    costs, returns = [], 0.0
    for _ in range(20):
        obs, reward, cost, terminated, truncated, info = env.step(rng.uniform(-1, 1, 6))
        returns = returns * 0.9 + 1.0
        costs.append(cost)
    assert obs.shape == (17,) and np.isfinite(obs).all()
    observation_wrapper = env.env.env
    assert observation_wrapper.obs_rms.count > 20  # reset + 20 steps (+ its epsilon)
    cost_wrapper = env
    expected = 1.0 / np.sqrt(cost_wrapper.return_rms.var + cost_wrapper.epsilon)
    assert costs[-1] == pytest.approx(expected)
    assert cost_wrapper.returns[0] == pytest.approx(returns)
    assert isinstance(reward, (float, np.floating))


def test_unsqueeze_refuses_vector_envs():
    envs = safety_gymnasium.vector.make(NAV_ID, num_envs=1, asynchronous=False)
    with pytest.raises(ValueError, match="vector"):
        SafeUnsqueeze(envs)
    envs.close()


def test_wrappers_forward_unknown_attributes_like_gymnasium_028():
    # SafePO (num_envs=1) saves ``env.obs_rms`` read through SafeUnsqueeze after its first epoch.
    env = safety_gymnasium.make(VEL_ID, max_episode_steps=4)
    env = SafeUnsqueeze(SafeNormalizeObservation(SafeRescaleAction(SafeAutoResetWrapper(env), -1.0, 1.0)))
    env.reset(seed=0)
    normalizer = env.env
    assert env.obs_rms is normalizer.obs_rms
    assert env.min_action.shape == env.action_space.shape  # SafeRescaleAction's, two layers down
    assert env.env_id == VEL_ID  # the unwrapped env's, through gymnasium's OrderEnforcing
    with pytest.raises(AttributeError, match="private"):
        env._elapsed_steps  # noqa: B018 - private names are not forwarded (as in 0.28)
    with pytest.raises(AttributeError, match="no_such_attribute"):
        env.no_such_attribute  # noqa: B018
    # set_wrapper_attr sets where the attribute lives, not on the outer wrapper
    replacement = type(normalizer.obs_rms)(shape=normalizer.obs_rms.mean.shape)
    env.set_wrapper_attr("obs_rms", replacement)
    assert normalizer.obs_rms is replacement and "obs_rms" not in vars(env)
    env.close()
    # around a vector env (SafePO's num_envs > 1 stack) forwarding reaches the vector env's attributes
    envs = SafeNormalizeReward(SafeNormalizeObservation(
        safety_gymnasium.vector.make(NAV_ID, num_envs=2, asynchronous=False)))
    assert envs.obs_rms is envs.env.obs_rms
    assert envs.single_observation_space == envs.env.env.single_observation_space
    envs.close()


def test_wrappers_are_rebuildable_from_their_spec():
    from gymnasium.utils.env_checker import check_env

    env = SafetyGymnasium2Gymnasium(safety_gymnasium.make(NAV_ID))
    check_env(env, skip_render_check=False)
    env.close()
    stacked = SafeUnsqueeze(SafeNormalizeReward(SafeRescaleAction(SafeAutoResetWrapper(bare()), -1.0, 1.0),
                                                gamma=0.9))
    names = [(spec.name, spec.kwargs) for spec in stacked.spec.additional_wrappers]
    assert names == [("SafeAutoResetWrapper", {}), ("SafeRescaleAction", {"min_action": -1.0, "max_action": 1.0}),
                     ("SafeNormalizeReward", {"gamma": 0.9, "epsilon": 1e-8}), ("SafeUnsqueeze", {})]
    stacked.close()
