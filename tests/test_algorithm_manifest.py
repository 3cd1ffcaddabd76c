"""The algorithm manifest: torch-free, the one list of names, and every table built from it agrees."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sg_torchrl.algorithms import manifest

ROOT = Path(__file__).resolve().parents[1]
SINGLE = ("pg", "ppo", "ppo_lag", "cppo_pid", "focops", "cup", "npg", "trpo", "trpo_lag", "rcpo", "cpo", "pcpo")
MULTI = ("mappo", "happo", "mappo_lag", "macpo")
OFF_POLICY = ("sac", "td3", "ddpg", "sac_lag", "td3_lag", "ddpg_lag", "sac_pid", "td3_pid", "ddpg_pid")
BEYOND_THE_PAPER = ("ppo_lag_pessimistic", *OFF_POLICY)


def _python(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=120)


def test_the_manifest_and_the_option_checks_import_without_torch():
    # The command line, the config check and the sweep report list and check algorithms in a second.
    result = _python(
        "import sys\n"
        "import sg_torchrl.algorithms.manifest\n"
        "assert 'torch' not in sys.modules and 'torchrl' not in sys.modules, 'manifest'\n"
        "import sg_torchrl.algorithms, sg_torchrl.train.config, sg_torchrl.sweep.report, sg_torchrl.sweep.grid\n"
        "assert 'torch' not in sys.modules, 'config or sweep'\n"
        "import sg_torchrl.train\n"
        "assert sg_torchrl.train.algorithm_title('mappo_lag') == 'MAPPO-Lag' and 'torch' not in sys.modules\n"
    )
    assert result.returncode == 0, result.stderr


def test_names_are_the_papers_in_its_order():
    # the paper's algorithms in its order, then those added beyond it
    assert manifest.names() == SINGLE + BEYOND_THE_PAPER + MULTI
    assert manifest.names(agents="single") == SINGLE + BEYOND_THE_PAPER and manifest.names(agents="multi") == MULTI
    assert manifest.SECOND_ORDER == {"npg", "trpo", "trpo_lag", "rcpo", "cpo", "pcpo", "macpo"}
    assert manifest.names(agents="multi", family="second_order") == ("macpo",)
    assert [manifest.get(name).title for name in ("ppo_lag", "cppo_pid", "trpo_lag", "mappo_lag")] == [
        "PPO-Lag", "CPPO-PID", "TRPO-Lag", "MAPPO-Lag"]
    assert [manifest.baseline(name) for name in ("cpo", "macpo", "not-an-algorithm")] == ["ppo", "mappo", "ppo"]


def test_an_unknown_name_lists_the_known_ones():
    with pytest.raises(KeyError, match="unknown algorithm 'sac2'; known: pg, ppo, .*, sac, .*, macpo"):
        manifest.get("sac2")
    with pytest.raises(ValueError, match="agents must be one of single, multi"):
        manifest.names(agents="both")


def test_rows_are_read_only():
    entry = manifest.get("pcpo")
    assert entry.defaults["line_search_steps"] == 200
    with pytest.raises(TypeError):
        entry.defaults["line_search_steps"] = 1  # type: ignore[index]


def test_the_config_views_derive_from_the_manifest():
    from sg_torchrl.train import config

    assert config.ALGORITHM_NAMES == SINGLE + ("ppo_lag_pessimistic",) and config.MULTI_AGENT_ALGORITHM_NAMES == MULTI
    assert config.OFF_POLICY_ALGORITHM_NAMES == OFF_POLICY == manifest.names(family="off_policy")
    assert config.SECOND_ORDER == manifest.SECOND_ORDER
    assert config.ALGORITHM_DEFAULTS == {entry.name: dict(entry.defaults) for entry in manifest.rows()}


def test_sg_train_help_lists_every_name():
    result = subprocess.run([sys.executable, "-m", "sg_torchrl.train", "--help"], capture_output=True, text=True,
                            cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "--algo {" + ",".join(manifest.names()) + "}" in result.stdout  # argparse's choices, in the manifest's order


@pytest.mark.parametrize("entry", manifest.ENTRIES, ids=lambda entry: entry.name)
def test_every_row_resolves_its_loss_and_builds(entry):
    torchrl_objectives = pytest.importorskip("torchrl.objectives")
    assert issubclass(entry.loss_class(), torchrl_objectives.LossModule)
    if entry.multi_agent:
        from sg_torchrl.train.multi_agent import MULTI_AGENT_ALGORITHMS

        assert callable(entry.round_class().for_seeds)  # the engine builds every seed's round from the class
        assert MULTI_AGENT_ALGORITHMS[entry.name].title == entry.title
    elif entry.off_policy:  # built by the off-policy engine from the row alone
        import torch
        from torchrl.data import Bounded

        from sg_torchrl.modules.off_policy import make_off_policy_networks
        from sg_torchrl.train.algorithms import make_multiplier
        from sg_torchrl.train.config import TrainConfig
        from sg_torchrl.train.off_policy import make_loss, off_policy_objective_of

        cfg, spec = TrainConfig(algo=entry.name), Bounded(-torch.ones(2), torch.ones(2), (2,))
        networks = make_off_policy_networks(3, spec, [4], stochastic=entry.name.startswith("sac"),
                                            num_critics=1 if entry.name.startswith("ddpg") else 2,
                                            constrained=entry.multiplier != "none")
        loss = make_loss(cfg, networks, make_multiplier(entry.multiplier, cfg), spec)
        assert entry.round_class() is None and isinstance(loss, entry.loss_class())
        assert off_policy_objective_of(loss).constrained == (entry.multiplier != "none")
    else:
        from sg_torchrl.train.algorithms import ALGORITHMS

        assert entry.round_class() is None and ALGORITHMS[entry.name].title == entry.title


def test_the_tables_hold_the_manifest_rows_in_order():
    pytest.importorskip("torchrl")
    from sg_torchrl.train.algorithms import ALGORITHMS
    from sg_torchrl.train.multi_agent import MULTI_AGENT_ALGORITHMS

    assert tuple(ALGORITHMS) == SINGLE + ("ppo_lag_pessimistic",) and tuple(MULTI_AGENT_ALGORITHMS) == MULTI
