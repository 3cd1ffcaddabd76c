"""sg_torchrl: Safety-Gymnasium environments and SafePO algorithms, TorchRL-native.

>>> import sg_torchrl
>>> env = sg_torchrl.make("SafetyHalfCheetahVelocity-v1", num_envs=4, seed=0)
>>> td = env.rollout(5)
>>> td["next", "cost"].shape
torch.Size([4, 5, 1])
"""

from sg_torchrl.envs import list_envs, make

__version__ = "0.1.0"
__all__ = ["make", "list_envs", "__version__"]
