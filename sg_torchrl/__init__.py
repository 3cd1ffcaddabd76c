"""sg_torchrl: Safety-Gymnasium environments and SafePO algorithms, TorchRL-native.

>>> import sg_torchrl
>>> env = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", num_envs=4, seed=0)
>>> td = env.rollout(5)
>>> td["next", "cost"].shape
torch.Size([4, 5, 1])

Importing the package loads neither torch nor MuJoCo (``make`` does, for the env it builds): the
registry is plain data, so ``sg-train`` and scripts can check env ids and options in about a second.
"""

from sg_torchrl.envs import list_envs, make

__version__ = "0.1.0"
__all__ = ["make", "list_envs", "__version__"]
