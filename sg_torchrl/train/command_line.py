"""``sg-train``'s command line: the parser built from :class:`~sg_torchrl.train.config.TrainConfig`'s fields.

Every field is a flag (``--steps-per-epoch``), typed and described by the field's annotation and help;
``--preset`` starts from a named preset; ``--env-options KEY=VALUE ...`` reads values as JSON. The config
checks itself (:meth:`~sg_torchrl.train.config.TrainConfig.validate`); this module only reads flags.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints
from types import UnionType

from sg_torchrl.train.config import ALGORITHM_DEFAULTS, PRESETS, TrainConfig
from sg_torchrl.validation import parse_bool

__all__ = ["build_parser", "command_line_values", "parse_args", "parse_env_option"]


def _flag_type(hint: Any):
    optional = [a for a in get_args(hint) if a is not type(None)] if get_origin(hint) in (Union, UnionType) else []
    if len(optional) == 1:  # ``X | None``: parse as X
        hint = optional[0]
    origin = get_origin(hint)
    if hint is bool:  # strictly one of true/false/1/0/yes/no; argparse names the flag in its error
        return _command_line_bool
    if origin is Literal:
        return str
    if origin is list:
        return int
    if origin is dict:
        return parse_env_option
    args = [a for a in get_args(hint) if a is not type(None)]
    return args[0] if args else hint


def _command_line_bool(text: str) -> bool:
    try:
        return parse_bool(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sg-train",
        description="Train a safe RL agent on a Safety-Gymnasium task (sg_torchrl).",
        epilog="exit status: 0 trained to the end; 1 the run diverged (a seed group: every seed); 2 a bad command "
               "line, run directory or checkpoint, refused before anything runs; 3 a file could not be written (a "
               "full disk or quota, a read-only or vanished directory, an output directory that is a file): the "
               "last checkpoint is intact and --resume continues from it; 128+N stopped by signal N (130 Ctrl-C, "
               "143 SIGTERM) after a checkpointed epoch.",
    )
    parser.add_argument("--preset", choices=sorted(PRESETS), help="start from a named preset, then apply flags")
    parser.add_argument("--task-module", dest="task_modules", action="append", metavar="MODULE",
                        help="import MODULE first (repeatable): a module of yours that registers env ids with "
                             "sg_torchrl.tasks (docs/custom_tasks.md); give it again with --resume")
    hints = get_type_hints(TrainConfig)
    for f in dataclasses.fields(TrainConfig):
        hint = hints[f.name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        # argparse default stays None so that explicitly given flags can be told apart (--resume).
        help_text = f"{f.metadata.get('help', '')} (default: {f.metadata.get('shown_default', default)})"
        kwargs: dict[str, Any] = {"type": _flag_type(hint), "help": help_text, "default": None}
        literal = next((a for a in (hint, *get_args(hint)) if get_origin(a) is Literal), None)  # also X | None
        if literal is not None:
            kwargs["choices"] = list(get_args(literal))
        if "choices" in f.metadata:  # a str field checked against a table (--algo: the algorithm manifest)
            kwargs["choices"] = list(f.metadata["choices"])
        if get_origin(hint) in (list, dict):
            kwargs["nargs"] = "+"
        if f.name == "seeds":
            kwargs["metavar"] = "SEED"
        if get_origin(hint) is dict:
            kwargs["metavar"] = "KEY=VALUE"
        if f.metadata.get("bare_flag"):  # ``--overwrite`` alone means true
            kwargs.update(nargs="?", const=True, metavar="BOOL")
        parser.add_argument("--" + f.name.replace("_", "-"), dest=f.name, **kwargs)
    return parser


def command_line_values(argv: list[str] | None = None) -> dict[str, Any]:
    """The field values a command line gives: its ``--preset``'s, then its flags' (unset fields absent).

    Nothing is validated against the defaults here: a resumed run (``--resume``) validates these
    merged over its saved config (:func:`sg_torchrl.train._resolve_resume`), a new run as they are.
    ``"preset"`` holds the preset's name when one was given.
    """
    parser = build_parser()
    namespace = parser.parse_args(argv)
    for module in namespace.task_modules or ():  # users' env ids, registered before anything reads the registry
        try:
            importlib.import_module(module)
        except ImportError as error:
            parser.error(f"--task-module {module}: {error}")
    if namespace.seed is not None and namespace.seeds is not None:
        parser.error("--seed and --seeds cannot be given together: --seed 3 trains one run, --seeds 3 4 5 a group "
                     "of runs (whose first seed is the group's)")
    values = dict(PRESETS[namespace.preset]) if namespace.preset else {}
    values.update({k: v for k, v in vars(namespace).items() if k not in ("preset", "task_modules") and v is not None})
    if isinstance(values.get("env_options"), list):  # [(key, value), ...] from the flag
        values["env_options"] = _command_line_env_options(values, dict(values["env_options"]))
    if namespace.preset:
        values["preset"] = namespace.preset
    return values


def _command_line_env_options(values: dict[str, Any], options: dict[str, Any]) -> dict[str, Any]:
    """``--env-options`` values (read as JSON) with the words true/false/1/0/yes/no of the env's bool
    options turned into bools: JSON reads ``compass=False`` as the string ``"False"``, which as a bool is
    true. The env id is the flag's, else the algorithm's default; a resumed run without ``--env-id`` keeps
    the strings, which the config check then refuses (never reads as true)."""
    from sg_torchrl.envs.registry import command_line_env_options

    env_id = values.get("env_id")
    if env_id is None and not values.get("resume"):
        env_id = ALGORITHM_DEFAULTS.get(values.get("algo", TrainConfig.algo), {}).get("env_id")
    return command_line_env_options(env_id, options) if env_id else options


def parse_args(argv: list[str] | None = None) -> TrainConfig:
    """Build a :class:`TrainConfig` from a preset and command-line overrides."""
    values = command_line_values(argv)
    values.pop("preset", None)
    return TrainConfig(**values)


def parse_env_option(text: str) -> tuple[str, Any]:
    """``"velocity_threshold=1.5"`` -> ``("velocity_threshold", 1.5)``: the value as JSON where it
    parses (numbers, ``true`` / ``false``, ``null``), else the string itself (``lidar=natural``)."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip().isidentifier():
        raise argparse.ArgumentTypeError(f"env option {text!r} is not KEY=VALUE (e.g. velocity_threshold=1.5)")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key.strip(), value
