"""Shared check that a seed gives simulator 0 the same trajectory whatever the batch size."""

from __future__ import annotations

import torch


def assert_sim0_same_for_any_batch(small, large, *, steps: int) -> None:
    """Step ``small`` (1 simulator) and ``large`` (N, same id, seed and episode length) with the same
    random actions through ``step_and_maybe_reset``; simulator 0's transitions must be identical, and
    simulator 0 must have been auto-reset in between (``steps`` longer than an episode)."""
    actions = 2 * torch.rand((steps, large.num_envs, *large.action_spec.shape[1:]),
                             generator=torch.Generator().manual_seed(0)) - 1
    outs = []
    for env in (small, large):
        td, trace = env.reset(), []
        for t in range(steps):
            stepped, td = env.step_and_maybe_reset(td.set("action", actions[t, : env.num_envs]))
            trace.append(stepped[0].clone())
        outs.append(trace)
    keys = ["observation", ("next", "observation"), ("next", "reward"), ("next", "cost"), ("next", "done")]
    keys += [("next", "cost_info", name) for name in small.constraint_names]
    for t, (a, b) in enumerate(zip(*outs)):
        for key in keys:
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=f"{key} at step {t}")
    assert any(step["next", "truncated"].item() for step in outs[0])  # an auto-reset happened in between
