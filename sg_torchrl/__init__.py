"""sg_torchrl: Safety-Gymnasium environments and SafePO algorithms, TorchRL-native.

>>> import sg_torchrl
>>> env = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", num_envs=4, seed=0)
>>> td = env.rollout(5)
>>> td["next", "cost"].shape
torch.Size([4, 5, 1])

Importing the package loads neither torch nor MuJoCo (``make`` does, for the env it builds): the
registry is plain data, so ``sg-train`` and scripts can check env ids and options in about a second.
The ids and their ``<Name>Gymnasium-v<k>`` twins are in gymnasium's registry from here on
(:mod:`sg_torchrl.gym_registration`; without importing gymnasium before a program does).
"""

from sg_torchrl.envs import list_envs, make
from sg_torchrl.gym_registration import register_when_gymnasium_loads

__version__ = "0.1.0"
__all__ = ["make", "list_envs", "load_policy", "register_cost_env", "register_task", "TaskSpec", "__version__"]

#: Names of :mod:`sg_torchrl.tasks` (users' own tasks), imported on first use: it loads the simulation stack.
_TASK_API = frozenset({"register_cost_env", "register_task", "TaskSpec"})


def load_policy(run_dir, seed=None, device="cpu"):
    """A trained run's policy with its observation normaliser folded in
    (:func:`sg_torchrl.evaluation.policy.load_policy`; imported here on first use)."""
    from sg_torchrl.evaluation.policy import load_policy as load

    return load(run_dir, seed=seed, device=device)


def __getattr__(name: str):
    if name in _TASK_API:
        from sg_torchrl import tasks

        return getattr(tasks, name)
    raise AttributeError(f"module 'sg_torchrl' has no attribute {name!r}")

# gymnasium.make / torchrl's GymEnv find the ids (and their "...Gymnasium-v<k>" twins) from here on.
register_when_gymnasium_loads()
