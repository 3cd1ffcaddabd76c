"""EpisodeStats: finished-episode return / cost / length across collector batches."""

import io
import sys
from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)
sys.path.insert(0, str(Path(__file__).parent))

from mock_envs import CountingCostEnv, expected_episode  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from sg_torchrl.collectors import EpisodeStats, make_collector, single_thread  # noqa: E402

NUM_ENVS = 4  # episode lengths 3, 4, 5, 6
STEPS_PER_BATCH = 7  # not a multiple of any episode length: episodes span batches
NUM_BATCHES = 6


def expected_finished(num_envs, steps, base_length=3):
    """Episodes in the order EpisodeStats reports them: by end step, then by env index."""
    rows = []
    for t in range(1, steps + 1):
        for i in range(num_envs):
            if t % (base_length + i) == 0:
                rows.append(expected_episode(base_length + i))
    return {key: [row[key] for row in rows] for key in rows[0]}


def as_lists(finished):
    return {key: value.tolist() for key, value in finished.items()}


@pytest.fixture(scope="module")
def batches():
    env = CountingCostEnv(NUM_ENVS)
    collector = make_collector(
        env,
        None,
        frames_per_batch=NUM_ENVS * STEPS_PER_BATCH,
        total_frames=NUM_ENVS * STEPS_PER_BATCH * NUM_BATCHES,
    )
    with single_thread():
        out = [batch.clone() for batch in collector]
    collector.shutdown()
    return out


def test_collector_layout(batches):
    assert len(batches) == NUM_BATCHES
    for batch in batches:
        assert batch.batch_size == (NUM_ENVS, STEPS_PER_BATCH)
        assert batch.names[-1] == "time"
        assert batch["next", "cost"].shape == (NUM_ENVS, STEPS_PER_BATCH, 1)


def test_matches_hand_computed_over_collector(batches):
    stats = EpisodeStats()
    for batch in batches:
        stats.update(batch)
    finished = stats.pop_finished()
    expected = expected_finished(NUM_ENVS, STEPS_PER_BATCH * NUM_BATCHES)
    assert as_lists(finished) == expected
    assert finished["length"].dtype == torch.int64
    assert stats.num_episodes == len(expected["return"])
    # popped: nothing left until the next episode ends
    assert all(v.numel() == 0 for v in stats.pop_finished().values())
    # one big batch gives the same episodes as the split batches
    whole = EpisodeStats()
    whole.update(torch.cat(batches, dim=1))
    assert as_lists(whole.pop_finished()) == expected


def test_window_and_metrics(batches):
    stats = EpisodeStats(history=5)
    assert stats.window() == {} and stats.metrics() == {}
    for batch in batches:
        stats.update(batch)
    expected = expected_finished(NUM_ENVS, STEPS_PER_BATCH * NUM_BATCHES)
    for n in (1, 3, 5, 50):
        window = stats.window(n)
        last = {key: values[-min(n, 5) :] for key, values in expected.items()}
        for key, values in last.items():
            assert window[key] == pytest.approx(sum(values) / len(values))
    metrics = stats.metrics(3)
    assert set(metrics) == {"Metrics/EpRet", "Metrics/EpCost", "Metrics/EpLen"}
    assert metrics["Metrics/EpCost"] == pytest.approx(stats.window(3)["cost"])


def test_single_env_time_layout(batches):
    # A [T] batch of one env (here env 1, episode length 4).
    stats = EpisodeStats()
    for batch in batches:
        stats.update(batch[1])
    steps = STEPS_PER_BATCH * NUM_BATCHES
    assert as_lists(stats.pop_finished())["return"] == [4.0] * (steps // 4)
    assert stats.num_envs == 1


def test_named_time_dim_first(batches):
    # [T, N] with the time dim named: same episodes as the collector's [N, T].
    stats = EpisodeStats()
    for batch in batches:
        stats.update(batch.transpose(0, 1))
    expected = expected_finished(NUM_ENVS, STEPS_PER_BATCH * NUM_BATCHES)
    assert as_lists(stats.pop_finished()) == expected


def test_state_dict_round_trip_mid_episode(batches):
    reference = EpisodeStats(history=4)
    first = EpisodeStats(history=4)
    for batch in batches[:3]:
        reference.update(batch)
        first.update(batch)
    assert (first.state_dict()["running"][0] > 0).any()  # some episodes are mid-way
    buffer = io.BytesIO()
    torch.save(first.state_dict(), buffer)
    buffer.seek(0)
    resumed = EpisodeStats(history=4)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    assert resumed.num_episodes == first.num_episodes
    for batch in batches[3:]:
        reference.update(batch)
        resumed.update(batch)
    assert resumed.num_episodes == reference.num_episodes
    assert resumed.window(4) == reference.window(4)
    assert as_lists(resumed.pop_finished()) == as_lists(reference.pop_finished())


def test_agent_dim_mean():
    num_envs, steps, agents = 2, 9, 3
    lengths = torch.tensor([2, 4])
    t = torch.arange(1, steps + 1)
    done = (t.unsqueeze(0) % lengths.unsqueeze(1) == 0).unsqueeze(-1)  # (N, T, 1) env level
    agent_scale = torch.arange(1.0, agents + 1)  # agent a gets (a+1) per step: mean 2
    reward = agent_scale.expand(num_envs, steps, agents).unsqueeze(-1).clone()
    cost = torch.zeros(num_envs, steps, agents, 1)
    cost[:, :, 0] = 3.0  # only agent 0 pays a cost: mean 1 per step
    batch = TensorDict(
        {
            "next": {
                "done": done,
                "agents": TensorDict(
                    {"reward": reward, "cost": cost}, batch_size=[num_envs, steps, agents]
                ),
            }
        },
        batch_size=[num_envs, steps],
    )
    stats = EpisodeStats(
        reward_key=("next", "agents", "reward"),
        cost_key=("next", "agents", "cost"),
        cost_info_key=("next", "agents", "cost_info"),
        agent_dim=-2,
    )
    stats.update(batch)
    finished = as_lists(stats.pop_finished())
    # ends: env0 at t=2,4,6,8; env1 at t=4,8 -> order (t, env)
    expected_lengths = [2, 2, 4, 2, 2, 4]
    assert finished["length"] == expected_lengths
    assert finished["return"] == [2.0 * n for n in expected_lengths]
    assert finished["cost"] == [1.0 * n for n in expected_lengths]
    assert set(finished) == {"return", "cost", "length"}

    with pytest.raises(ValueError, match="agent_dim"):
        EpisodeStats(reward_key=("next", "agents", "reward"), cost_key=None).update(batch)


def test_random_batches_match_sequential_loop():
    # Random rewards / costs / dones split into uneven batches vs a plain per-step loop.
    gen = torch.Generator().manual_seed(0)
    num_envs, steps = 5, 60
    reward = torch.randn(num_envs, steps, 1, generator=gen)
    cost = torch.rand(num_envs, steps, 1, generator=gen)
    done = torch.rand(num_envs, steps, 1, generator=gen) < 0.2
    data = TensorDict(
        {"next": {"reward": reward, "cost": cost, "done": done}}, batch_size=[num_envs, steps]
    )
    stats = EpisodeStats()
    for start, stop in [(0, 1), (1, 13), (13, 14), (14, 40), (40, 60)]:
        stats.update(data[:, start:stop])
    got = stats.pop_finished()

    expected = {"return": [], "cost": [], "length": []}
    running = torch.zeros(num_envs, 3, dtype=torch.float64)
    for t in range(steps):
        running[:, 0] += reward[:, t, 0].double()
        running[:, 1] += cost[:, t, 0].double()
        running[:, 2] += 1
        for i in range(num_envs):
            if done[i, t]:
                for c, key in enumerate(expected):
                    expected[key].append(running[i, c].item())
                running[i] = 0
    assert got["length"].tolist() == [int(n) for n in expected["length"]]
    for key in ("return", "cost"):
        torch.testing.assert_close(got[key], torch.tensor(expected[key], dtype=torch.float64))
    torch.testing.assert_close(stats.state_dict()["running"][:2], running[:, :2].T)
