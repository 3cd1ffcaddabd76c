"""Your own navigation task: declare it, register an id, train it (docs/custom_tasks.md).

    python examples/custom_task.py --total-steps 20000
    sg-train --task-module examples.custom_task --env-id SafetyPointCrowdedGoal-v0   # the same id from the CLI
"""

import argparse

import sg_torchrl
from sg_torchrl.tasks import TaskSpec, register_task

CROWDED_GOAL = TaskSpec(
    "CrowdedGoal",
    objective="goal",
    extents=2.0,  # robot and objects are placed in [-2, 2] x [-2, 2]
    objects={
        "goal": {"keepout": 0.3},
        "hazards": {"count": 12, "size": 0.25, "keepout": 0.2},  # each costs the depth the robot is inside it
        "pillars": {"count": 3, "cost": False},  # in the way, free to touch
    },
    reward={"distance": 1.0, "goal": 2.0},
    max_episode_steps=500,
)
ENV_ID = "SafetyPointCrowdedGoal-v0"
if ENV_ID not in sg_torchrl.list_envs():  # importing the module twice registers once
    register_task(ENV_ID, CROWDED_GOAL, robot="Point")


def train(total_steps: int, output_dir: str = "runs") -> dict:
    from sg_torchrl.train import TrainConfig, train

    cfg = TrainConfig(algo="ppo_lag", env_id=ENV_ID, total_steps=total_steps, steps_per_epoch=total_steps // 2,
                      num_envs=2, output_dir=output_dir, overwrite=True, eval_episodes=0)
    return train(cfg)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--total-steps", type=int, default=20_000)
    metrics = train(parser.parse_args().total_steps)
    nan = float("nan")
    print(f"EpRet {metrics.get('Metrics/EpRet', nan):.2f}  EpCost {metrics.get('Metrics/EpCost', nan):.2f}")
