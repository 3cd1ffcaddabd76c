"""``sg-eval RUN_DIR``: evaluate, watch and export the policies of an ``sg-train`` run.

Runs ``--episodes`` episodes of each seed's policy (every seed of a seed group's directory, or those
``--seeds`` names), prints a table (a row per seed and their mean) and writes into the output
directory (default ``RUN_DIR/eval/``) ``episodes.csv`` (each episode's return, cost and length) and
``summary.json`` (per seed and mean, under the names ``sg-train``'s ``summary.json`` uses).

**Defaults reproduce training's own evaluation.** At the end of a run the trainer evaluates each
seed's mean action on ``eval_episodes`` episodes of its env (with its ``env_options``), one per
simulator of an env seeded ``env_seed(run seed, EVALUATION)`` (run seed + 10,000,
:mod:`sg_torchrl.seeding`), with its frozen observation normaliser and ``threads`` torch threads
(:func:`~sg_torchrl.train.evaluate.evaluate_policy`). ``sg-eval``'s defaults are exactly these, read
from the run's checkpoint, and it runs the same rollout code
(:func:`~sg_torchrl.train.evaluate.evaluate_episodes`), so without options its ``Metrics/EvalEpRet``,
``Metrics/EvalEpCost``, ... equal those of the run's ``summary.json``, to the last bit. ``--seed``,
``--episodes``, ``--env-id``, ``--env-options`` and ``--stochastic`` evaluate otherwise. This holds for every
family: single-agent on-policy and off-policy runs (SAC's squashed mean, TD3's and DDPG's deterministic
actor) and multi-agent runs (the team's mean actions, its per-agent normaliser; the team return is the
agents' mean reward summed over the episode, as training scores it). Episode ``k`` starts
from the same layout whatever ``--episodes`` (simulator ``k``'s seed does not depend on their number), but its
figures are bit-identical only for the same number: the policy acts on all episodes in one batch, and a
matmul over another batch size rounds differently (about 1e-7 per action, 1e-3 in a 1000-step return of
PointGoal1).

``--video out.mp4`` (or ``.gif``) records the first ``--video-episodes`` evaluated episodes, tiled, each
with its running return and cost (:mod:`~sg_torchrl.evaluation.video`); ``--export policy.pt2`` writes
the mean action as a ``torch.export`` program that runs with torch alone
(:mod:`~sg_torchrl.evaluation.export`). With several seeds each gets its own file (``out-seed-001.mp4``).
``--episodes 0`` exports without evaluating.

Nothing is overwritten without ``--overwrite``; files are written atomically
(:mod:`sg_torchrl.train.writes`). Exit status: 0 done; 2 a bad command line, run or checkpoint,
refused before anything is written; 3 a file could not be written.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path
from typing import Any

from sg_torchrl.train.config import parse_env_option
from sg_torchrl.train.writes import EXIT_WRITE_FAILED, RunWriteError, make_dirs, write_atomic

__all__ = ["build_parser", "main"]

EPISODES_FILE = "episodes.csv"
SUMMARY_FILE = "summary.json"
EXIT_BAD_ARGUMENTS = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sg-eval",
        description="Evaluate, watch and export the trained policies of an sg-train run (sg_torchrl). Without "
                    "options it repeats the evaluation sg-train ran at the end of training, figure for figure.",
        epilog="exit status: 0 done; 2 a bad command line, run directory or checkpoint (nothing written); 3 a file "
               "could not be written (a full disk, a read-only directory, an output path that is a file).",
    )
    parser.add_argument("run_dir", metavar="RUN_DIR", help="a run's directory (sg-train's), a seed group's, one of "
                        "its seed-XXX/ directories, or a checkpoint.pt")
    parser.add_argument("--seeds", type=int, nargs="+", metavar="SEED",
                        help="the seeds of a group to evaluate (default: every seed)")
    parser.add_argument("--episodes", type=int, help="episodes per seed (default: the run's eval_episodes, 10 "
                        "unless it was trained otherwise; 0: no evaluation, e.g. only --export)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions from the policy's distribution "
                        "(its Gaussian, SAC's squashed one; torch's RNG seeded with the env seed) instead of its mean "
                        "action; TD3 and DDPG actors are deterministic")
    parser.add_argument("--seed", type=int, help="env seed of the evaluation env (default: each run seed's "
                        "evaluation seed, run seed + 10000, as sg-train evaluates)")
    parser.add_argument("--env-id", help="evaluate on another env id with the same observations and actions "
                        "(default: the run's)")
    parser.add_argument("--env-options", "--env-option", dest="env_options", type=parse_env_option, nargs="+",
                        action="extend", metavar="KEY=VALUE",
                        help="task options over the run's own (as sg-train --env-options takes them)")
    parser.add_argument("--output-dir", type=Path, help="where episodes.csv and summary.json go (default: "
                        "RUN_DIR/eval)")
    parser.add_argument("--overwrite", action="store_true", help="replace an earlier evaluation's files, video "
                        "or export")
    parser.add_argument("--video", type=Path, metavar="PATH.mp4|gif",
                        help="record evaluated episodes with their running return and cost")
    parser.add_argument("--video-episodes", type=int, default=1, help="episodes shown, tiled (default: 1)")
    parser.add_argument("--video-size", type=int, nargs=2, default=(256, 256), metavar=("WIDTH", "HEIGHT"),
                        help="one episode's picture in pixels (default: 256 256)")
    parser.add_argument("--camera", help="camera name (default: the env's, following the robot)")
    parser.add_argument("--export", type=Path, metavar="PATH",
                        help="write the mean action as a torch.export program (torch.export.load(PATH).module())")
    parser.add_argument("--device", default="cpu", help="where the policy runs (default: cpu)")
    parser.add_argument("--threads", type=int, help="torch threads (default: the run's, as it evaluated)")
    return parser


def _seed_path(path: Path, seed: int, several: bool) -> Path:
    """``path`` for one seed: itself, or ``<stem>-seed-XXX<suffix>`` when several seeds are written."""
    return path.with_name(f"{path.stem}-seed-{seed:03d}{path.suffix}") if several else path


class _Refused(Exception):
    """A bad command line, run or checkpoint: printed, exit status 2."""


def _check_arguments(args: argparse.Namespace) -> None:
    if args.episodes is not None and args.episodes < 0:
        raise _Refused(f"--episodes must be >= 0, got {args.episodes}")
    if args.video_episodes < 1:
        raise _Refused(f"--video-episodes must be >= 1, got {args.video_episodes}")
    if min(args.video_size) < 16:
        raise _Refused(f"--video-size must be at least 16 pixels a side, got {args.video_size}")
    if args.threads is not None and args.threads < 1:
        raise _Refused(f"--threads must be >= 1, got {args.threads}")
    if args.video is not None:
        from sg_torchrl.evaluation.video import check_video_path

        check_video_path(args.video)


def _plan(args: argparse.Namespace, run: Any) -> dict[str, Any]:
    """What to do, checked against the run: seeds, episodes, env, output files. Raises _Refused / ValueError."""
    from sg_torchrl.envs.registry import command_line_env_options, validate_env_options

    cfg = run.config
    seeds = args.seeds or ([run.default_seed] if run.default_seed is not None else list(run.seeds))
    for seed in seeds:
        run.pick_seed(seed)  # a clear error for a seed the run does not hold
    episodes = args.episodes if args.episodes is not None else (cfg.eval_episodes or 10)
    env_id = args.env_id or cfg.env_id
    options = dict(cfg.env_options)
    given = dict(args.env_options or [])
    options.update(command_line_env_options(env_id, given))
    reserved = sorted(set(given) & {"num_envs", "seed", "device"})
    if reserved:
        raise _Refused(f"--env-options cannot set {', '.join(reserved)} (use --episodes / --seed)")
    validate_env_options(env_id, options)
    if args.video is not None and args.video_episodes > episodes:
        raise _Refused(f"--video-episodes {args.video_episodes} is more than the {episodes} episodes evaluated")
    output = args.output_dir or run.path.parent / "eval"
    several = len(seeds) > 1
    targets = []
    if episodes:
        targets += [output / EPISODES_FILE, output / SUMMARY_FILE]
        if args.video is not None:
            targets += [_seed_path(args.video, seed, several) for seed in seeds]
    elif args.video is not None:
        raise _Refused("--video records evaluated episodes: give --episodes >= 1")
    if args.export is not None:
        targets += [_seed_path(args.export, seed, several) for seed in seeds]
    existing = [str(path) for path in targets if path.exists()]
    if existing and not args.overwrite:
        raise _Refused(f"{', '.join(existing)} already exist{'s' if len(existing) == 1 else ''} (an earlier "
                       f"evaluation); pass --overwrite to replace, or --output-dir / another path")
    if args.video is not None and episodes:
        from sg_torchrl.envs.rendering import gl_backend

        gl_backend()  # RenderingUnavailable (a RuntimeError) says what is missing
    return {"seeds": seeds, "episodes": episodes, "env_id": env_id, "env_options": options, "output": output,
            "several": several}


def _check_observations(policy: Any, env_id: str, options: dict[str, Any]) -> None:
    """Refuse an env whose observations or actions differ from what the policy was trained on."""
    import sg_torchrl

    env = sg_torchrl.make(env_id, num_envs=1, **options)
    try:
        observations = {key: tuple(env.observation_spec[key].shape[1:]) if key in env.observation_spec.keys(True)
                        else None for key in policy.in_keys}
        actions = tuple(env.full_action_spec[env.action_key].shape[1:])
    finally:
        env.close()
    if observations != policy.input_shapes or actions != policy.action_shape:
        raise _Refused(f"{env_id} with {options} emits {observations} and takes actions of shape {actions}; the "
                       f"policy was trained on {policy.input_shapes} with actions of shape {policy.action_shape}")


def _evaluate(args: argparse.Namespace, run: Any, plan: dict[str, Any]) -> dict[str, Any]:
    """Evaluate (and record, export) every seed of the plan; returns each seed's summary and episodes."""
    import torch
    from torchrl.envs.utils import ExplorationType

    from sg_torchrl import seeding
    from sg_torchrl.evaluation.export import export_policy
    from sg_torchrl.evaluation.policy import policy_of
    from sg_torchrl.evaluation.video import EvaluationVideo
    from sg_torchrl.train.evaluate import evaluate_episodes, summarize_episodes

    torch.set_num_threads(args.threads or run.config.threads)
    exploration = ExplorationType.RANDOM if args.stochastic else ExplorationType.DETERMINISTIC
    results: dict[int, dict[str, Any]] = {}
    for seed in plan["seeds"]:
        policy = policy_of(run, seed, args.device)
        if args.stochastic and not policy.stochastic:
            raise _Refused(f"--stochastic samples the policy's action distribution; a {run.config.algo} actor is "
                           f"deterministic (its exploration noise is part of training only)")
        if plan["env_id"] != policy.config.env_id or plan["env_options"] != policy.config.env_options:
            _check_observations(policy, plan["env_id"], plan["env_options"])
        result: dict[str, Any] = {"policy": policy}
        if args.export is not None:
            result["export"] = export_policy(policy, _seed_path(args.export, seed, plan["several"]))
        if plan["episodes"]:
            env_seed = args.seed if args.seed is not None else seeding.env_seed(seed, seeding.Purpose.EVALUATION)
            video = None
            if args.video is not None:
                width, height = args.video_size
                video = EvaluationVideo(_seed_path(args.video, seed, plan["several"]), args.video_episodes,
                                        width=width, height=height, camera=args.camera)
            try:
                with torch.random.fork_rng(devices=[]):
                    seeding.seed_torch(env_seed)  # --stochastic's action noise: reproducible from the env seed
                    episodes = evaluate_episodes(plan["env_id"], policy, plan["episodes"], seed=env_seed,
                                                 env_options=plan["env_options"], exploration=exploration,
                                                 callback=video)
            except BaseException:
                if video is not None:
                    video.discard()
                raise
            if video is not None:
                result["video"] = video.close()
            result.update(env_seed=env_seed, episodes=episodes, summary=summarize_episodes(episodes))
        results[seed] = result
    return results


def _write_results(args: argparse.Namespace, run: Any, plan: dict[str, Any], results: dict[int, Any]) -> dict:
    from sg_torchrl.train.seed_runs import mean_row

    rows = io.StringIO()
    writer = csv.writer(rows, lineterminator="\n")
    writer.writerow(["seed", "episode", "env_seed", "return", "cost", "length"])
    seeds: dict[str, Any] = {}
    for seed, result in results.items():
        episodes = result["episodes"]
        for k in range(plan["episodes"]):
            writer.writerow([seed, k, result["env_seed"], repr(episodes["return"][k].item()),
                             repr(episodes["cost"][k].item()), int(episodes["length"][k].item())])
        policy = result["policy"]
        seeds[str(seed)] = {**result["summary"], "env_seed": result["env_seed"], "checkpoint_epoch": policy.epoch,
                            **({"Diverged": True, "DivergedEpoch": policy.diverged["epoch"]} if policy.diverged else {})}
    live = [s for s in seeds.values() if not s.get("Diverged")]
    metric_names = [name for name in seeds[next(iter(seeds))] if name.startswith("Metrics/")]
    mean = mean_row([{name: s[name] for name in metric_names} for s in live])
    cfg = run.config
    summary = {
        "run_dir": str(run.path.parent), "algo": cfg.algo, "env_id": plan["env_id"], "env_options": plan["env_options"],
        "episodes": plan["episodes"], "deterministic": not args.stochastic, "seeds": seeds, "mean": mean,
        "mean_over_seeds": [int(seed) for seed, s in seeds.items() if not s.get("Diverged")],
    }
    make_dirs(plan["output"])
    write_atomic(plan["output"] / EPISODES_FILE, rows.getvalue())
    write_atomic(plan["output"] / SUMMARY_FILE, json.dumps(summary, indent=2))
    return summary


def _print_table(args: argparse.Namespace, run: Any, plan: dict[str, Any], summary: dict[str, Any]) -> None:
    from sg_torchrl.train import algorithm_title

    how = "stochastic" if args.stochastic else "deterministic"
    env_seed = f"env seed {args.seed}" if args.seed is not None else "env seed: run seed + 10000, as sg-train"
    print(f"{algorithm_title(run.config.algo)} on {plan['env_id']}: {plan['episodes']} {how} episodes per seed "
          f"({env_seed})")
    print(f"  {'seed':>6}  {'EpRet':>9} {'(std)':>8}  {'EpCost':>8} {'(std)':>8}  {'EpLen':>7}")

    def line(name: str, s: dict[str, float], note: str = "") -> str:
        return (f"  {name:>6}  {s['Metrics/EvalEpRet']:9.2f} {'(' + format(s['Metrics/EvalEpRetStd'], '.2f') + ')':>8}  "
                f"{s['Metrics/EvalEpCost']:8.2f} {'(' + format(s['Metrics/EvalEpCostStd'], '.2f') + ')':>8}  "
                f"{s['Metrics/EvalEpLen']:7.1f}{note}")

    for seed, s in summary["seeds"].items():
        print(line(seed, s, f"   (diverged in epoch {s['DivergedEpoch']})" if s.get("Diverged") else ""))
    if len(summary["seeds"]) > 1 and summary["mean"]:
        print(line("mean", summary["mean"]))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        _check_arguments(args)
    except SystemExit as stop:  # --help (0), or a bad flag (2) with its "sg-eval: error:" line
        return stop.code if isinstance(stop.code, int) else EXIT_BAD_ARGUMENTS
    except (_Refused, ValueError) as error:
        print(f"sg-eval: error: {error}", file=sys.stderr)
        return EXIT_BAD_ARGUMENTS
    from sg_torchrl.envs.rendering import RenderingUnavailable
    from sg_torchrl.evaluation.policy import read_run

    try:
        run = read_run(args.run_dir)
        plan = _plan(args, run)
        results = _evaluate(args, run, plan)
        summary = _write_results(args, run, plan, results) if plan["episodes"] else None
    except RunWriteError as error:
        print(f"sg-eval: error: {error}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    except (_Refused, ValueError, FileNotFoundError, RenderingUnavailable) as error:
        print(f"sg-eval: error: {error}", file=sys.stderr)
        return EXIT_BAD_ARGUMENTS
    if summary is not None:
        _print_table(args, run, plan, summary)
        print(f"  wrote: {plan['output'] / EPISODES_FILE}, {plan['output'] / SUMMARY_FILE}")
    for result in results.values():
        for what in ("video", "export"):
            if result.get(what) is not None:
                print(f"  {what}: {result[what]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
