"""``backend="warp"``: :class:`~sg_torchrl.envs.warp_physics.WarpBatch` against MuJoCo C.

Skipped as a whole without MuJoCo Warp (``pip install 'sg_torchrl[warp]'``). Without a GPU the tests
run on Warp's ``"cpu"`` device; its kernels compile on first use (about 90 s for the HalfCheetah
model on a busy 2-core machine, then cached in ``~/.cache/warp``), so the envs are built once per
module. The two-hand test compiles its own kernels (about 140 s) and is marked ``slow``; the GPU
test runs only where torch and Warp both see CUDA.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("mujoco_warp", reason="MuJoCo Warp is not installed: pip install 'sg_torchrl[warp]'")

from torchrl.envs.utils import check_env_specs  # noqa: E402

from sg_torchrl.envs import make  # noqa: E402
from sg_torchrl.envs.velocity.robots import load_model  # noqa: E402
from sg_torchrl.envs.warp_physics import WarpBatch  # noqa: E402

ENV_ID = "SafetyHalfCheetahVelocity-v1"
N = 3
#: MuJoCo Warp computes in float32: the same start state and actions give trajectories that agree to
#: float32 rounding (~1e-7 relative) at first, growing by roughly 10x every few steps of this chaotic
#: robot (measured on Warp's CPU device: 3e-7 after 1 step, 8e-7 after 5, 5e-6 after 10, 2e-3 after 20).
#: Five steps (25 physics steps) with 1e-4 leaves two orders of magnitude of margin.
STEPS, QPOS_TOL = 5, 1e-4


def _actions(steps: int, seed: int = 0) -> list[torch.Tensor]:
    rng = np.random.default_rng(seed)
    return [torch.as_tensor(rng.uniform(-1, 1, (N, 6)), dtype=torch.float32) for _ in range(steps)]


def _step(env, td, action):
    return env.step(td.set("action", action))["next"].exclude("action")


@pytest.fixture(scope="module")
def envs():
    """``(warp, cpu)`` HalfCheetah envs with ``N`` simulators (the Warp kernels compile here, once)."""
    warp_env = make(ENV_ID, num_envs=N, seed=1, backend="warp", warp_device="cpu")
    cpu_env = make(ENV_ID, num_envs=N, seed=1)
    yield warp_env, cpu_env
    warp_env.close()
    cpu_env.close()


def test_physics_is_a_warp_batch(envs):
    warp_env, _ = envs
    assert isinstance(warp_env.physics, WarpBatch)
    assert warp_env.physics.device == "cpu"


def test_specs_and_sizes_match_the_cpu_backend(envs):
    warp_env, cpu_env = envs
    for spec in ("full_observation_spec", "full_action_spec", "full_reward_spec", "full_done_spec"):
        assert getattr(warp_env, spec) == getattr(cpu_env, spec), spec
    assert warp_env.batch_size == cpu_env.batch_size
    assert warp_env.physics.qpos().shape == cpu_env.physics.qpos().shape
    assert warp_env.physics.qvel().shape == cpu_env.physics.qvel().shape
    assert warp_env.physics.qpos().dtype == np.float64  # the envs' numpy code sees the CPU backend's dtype
    check_env_specs(warp_env, seed=0)


def test_the_multi_agent_form_takes_the_backend_too():
    env = make("Safety2x3HalfCheetahVelocity-v0", num_envs=2, seed=0, backend="warp", warp_device="cpu")
    try:
        assert isinstance(env.physics, WarpBatch)
        td = env.rollout(3, break_when_any_done=False)
        assert torch.isfinite(td["next", "agents", "observation"]).all()
    finally:
        env.close()


def test_rollout_matches_mujoco_c_to_float32_precision(envs):
    warp_env, cpu_env = envs
    warp_env.set_seed(7)
    cpu_env.set_seed(7)
    td_warp, td_cpu = warp_env.reset(), cpu_env.reset()
    # The same reset draws; Warp stores them as float32.
    np.testing.assert_allclose(warp_env.physics.qpos(), cpu_env.physics.qpos(), rtol=0, atol=1e-7)
    for action in _actions(STEPS):
        td_warp, td_cpu = _step(warp_env, td_warp, action), _step(cpu_env, td_cpu, action)
    np.testing.assert_allclose(warp_env.physics.qpos(), cpu_env.physics.qpos(), rtol=0, atol=QPOS_TOL)
    torch.testing.assert_close(td_warp["observation"], td_cpu["observation"], rtol=0, atol=10 * QPOS_TOL)
    torch.testing.assert_close(td_warp["reward"], td_cpu["reward"], rtol=0, atol=10 * QPOS_TOL)
    torch.testing.assert_close(td_warp["cost"], td_cpu["cost"])


def test_resetting_some_worlds_leaves_the_others_untouched(envs):
    warp_env, _ = envs
    td = warp_env.reset()
    for action in _actions(3, seed=1):
        td = _step(warp_env, td, action)
    physics = warp_env.physics
    qpos, qvel, time = physics.qpos().copy(), physics.qvel().copy(), physics.torch_view("time").clone()
    td = warp_env.reset(td.set("_reset", torch.tensor([[False], [True], [False]])))
    keep = [0, 2]
    np.testing.assert_array_equal(physics.qpos()[keep], qpos[keep])
    np.testing.assert_array_equal(physics.qvel()[keep], qvel[keep])
    assert torch.equal(physics.torch_view("time")[keep], time[keep])
    assert physics.torch_view("time")[1] == 0
    assert not np.array_equal(physics.qpos()[1], qpos[1])


def test_partial_reset_restores_the_derived_fields_of_the_other_worlds():
    """``forward`` runs on every world: the cached fields of the worlds not reset are put back."""
    model = load_model("half_cheetah.xml")
    batch = WarpBatch(model, N, fields=("xpos",), device="cpu")  # positions lag the state (no forward after step)
    rng = np.random.default_rng(0)
    for _ in range(3):
        batch.step(rng.uniform(-1, 1, (N, model.nu)), 5)
    xpos = batch.field("xpos").copy()
    batch.reset([1], model.qpos0[None] + 0.1, np.zeros((1, model.nv)))
    np.testing.assert_array_equal(batch.field("xpos")[[0, 2]], xpos[[0, 2]])
    assert not np.array_equal(batch.field("xpos")[1], xpos[1])


def test_a_diverged_world_is_reported_and_reset_while_the_others_continue(envs):
    warp_env, _ = envs
    td = warp_env.reset()
    physics = warp_env.physics
    state, action = physics.get_state(), _actions(1, seed=2)[0]
    clean = _step(warp_env, td.clone(), action)
    clean_qpos = physics.qpos().copy()

    physics.set_state(state)  # the same start, with world 1 poisoned
    physics.torch_view("qvel")[1] = float("nan")
    errors = warp_env.physics_errors
    poisoned = _step(warp_env, td.clone(), action)
    assert warp_env.physics_errors == errors + 1  # physics.unstable named it; the env then reset it with a new draw
    assert poisoned["truncated"].flatten().tolist() == [False, True, False]
    assert torch.isfinite(poisoned["observation"]).all()
    assert np.isfinite(physics.qpos()).all() and np.isfinite(physics.qvel()).all()
    # The others stepped exactly as without the poisoned world (Warp's CPU device is deterministic).
    np.testing.assert_array_equal(physics.qpos()[[0, 2]], clean_qpos[[0, 2]])
    torch.testing.assert_close(poisoned["observation"][[0, 2]], clean["observation"][[0, 2]], rtol=0, atol=0)
    _step(warp_env, poisoned, action)
    assert not physics.unstable.any()


def test_the_physics_resets_a_diverged_world_to_the_initial_state():
    model = load_model("half_cheetah.xml")
    batch = WarpBatch(model, N, device="cpu")
    batch.torch_view("qvel")[1] = float("nan")
    unstable = batch.step(np.zeros((N, model.nu)), 2)
    assert unstable.tolist() == [False, True, False]
    np.testing.assert_allclose(batch.qpos()[1], model.qpos0, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(batch.qvel()[1], 0.0)
    assert batch.torch_view("time")[1] == 0 and batch.torch_view("time")[0] > 0
    assert not batch.step(np.zeros((N, model.nu)), 2).any()


def test_a_buffer_overflow_warns_once_naming_the_size_to_raise():
    model = load_model("half_cheetah.xml")
    batch = WarpBatch(model, 2, device="cpu", njmax=4)  # the cheetah on the floor needs more constraint rows
    with pytest.warns(RuntimeWarning, match=r"raise nconmax \(now 64\) or njmax \(now 4\)"):
        for _ in range(30):
            batch.step(np.zeros((2, model.nu)), 5)


def test_buffer_sizes_reach_the_physics_through_warp_options():
    env = make(ENV_ID, num_envs=2, backend="warp", warp_device="cpu", warp_options={"njmax": 96, "nconmax": 32})
    assert env.physics.warp_data.njmax == 96
    assert env.physics.warp_data.naconmax == 2 * 32


def test_state_round_trip_replays_exactly(envs):
    warp_env, _ = envs
    td = warp_env.reset()
    physics = warp_env.physics
    state = physics.get_state()
    assert state.shape[0] == N and state.dtype == np.float64
    actions = _actions(2, seed=4)
    for action in actions:
        td = _step(warp_env, td, action)
    first = physics.qpos().copy()
    physics.set_state(state)
    for action in actions:
        _step(warp_env, td, action)
    np.testing.assert_array_equal(physics.qpos(), first)
    with pytest.raises(ValueError, match="columns"):
        physics.set_state(state[:, :-1])


def test_datas_copies_a_world_to_the_host_for_rendering(envs):
    warp_env, _ = envs
    physics = warp_env.physics
    assert len(physics.datas) == N
    np.testing.assert_array_equal(physics.datas[2].qpos, physics.qpos()[2])
    np.testing.assert_array_equal(physics.datas[-1].qvel, physics.qvel()[2])
    with pytest.raises(IndexError):
        physics.datas[N]


def test_render_draws_a_host_copy_of_the_world(envs, backend):
    """``render`` works unchanged (``backend`` is conftest's headless OpenGL fixture, not the physics)."""
    frame = envs[0].render(1, 64, 48)
    assert frame.shape == (48, 64, 3) and frame.std() > 0


def test_torch_views_alias_the_warp_arrays(envs):
    physics = envs[0].physics
    view = physics.torch_view("qpos")
    assert view.data_ptr() == physics.warp_data.qpos.ptr
    assert view.shape == (N, physics.model.nq) and view.dtype == torch.float32


def test_navigation_only_features_say_they_are_not_ported(envs):
    physics = envs[0].physics
    mask = np.ones(physics.model.ngeom, dtype=bool)
    with pytest.raises(NotImplementedError, match="not ported"):
        physics.count_contacts(mask, mask)
    with pytest.raises(NotImplementedError, match="not ported"):
        physics.contact_counts(mask)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (and a CUDA build of torch)")
def test_cuda_tensors_are_on_the_gpu_and_zero_copy():
    import warp as wp

    if not wp.is_cuda_available():
        pytest.skip("Warp sees no CUDA device")
    model = load_model("half_cheetah.xml")
    batch = WarpBatch(model, 4, device="cuda:0")
    for name in ("qpos", "qvel", "ctrl"):
        view = batch.torch_view(name)
        assert view.is_cuda
        assert view.data_ptr() == getattr(batch.warp_data, name).ptr
    # Graph replay (third step on) gives what plain launches give.
    plain = WarpBatch(model, 4, device="cuda:0", graph=False)
    ctrl = np.random.default_rng(0).uniform(-1, 1, (4, model.nu))
    for _ in range(4):
        batch.step(ctrl, 5)
        plain.step(ctrl, 5)
    np.testing.assert_allclose(batch.qpos(), plain.qpos(), rtol=0, atol=1e-5)


@pytest.mark.slow
def test_two_hands_step_on_warp():
    """ShadowHandOverSafeJoint on Warp: finite 398-entry observations and a cost (compiles ~140 s on a CPU)."""
    env = make("ShadowHandOverSafeJoint-v0", num_envs=2, seed=0, backend="warp", warp_device="cpu")
    try:
        td = env.reset()
        for _ in range(2):
            td = env.step(td.set("action", env.action_spec.rand()))["next"].exclude("action")
        assert td["observation"].shape == (2, 398)
        assert torch.isfinite(td["observation"]).all()
        assert "cost" in td.keys() and ("cost_info", "forefinger_abduction") in td.keys(True)
        assert not env.physics.unstable.any()
    finally:
        env.close()
