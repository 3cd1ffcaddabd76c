"""``SafetyAsyncVectorEnv``: 6-tuple envs stepped in worker processes, with an explicit start method.

Why the start method matters: importing TorchRL (which sg_torchrl does) sets Python's *global*
multiprocessing start method to ``spawn``. A spawned worker re-imports the script that started it,
so a Safety-Gymnasium script without an ``if __name__ == "__main__":`` guard (they ran under
``fork`` on Linux) would start its training again in every worker. This env therefore never uses
the global default: ``context=None`` means ``"fork"`` where the platform has it (Linux) and
``"spawn"`` elsewhere (macOS, Windows: there the original's default was ``spawn`` too). Pass
``context="spawn"`` / ``"forkserver"`` to choose.
"""

from __future__ import annotations

import multiprocessing as mp
import sys
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import cloudpickle
import gymnasium

from sg_torchrl.safety_gymnasium.vector.utils import autoreset_step, set_wrapper_attr, wrapper_attr
from sg_torchrl.safety_gymnasium.vector.vector_env import SafeVectorEnv

__all__ = ["SafetyAsyncVectorEnv", "default_context"]


def default_context() -> str:
    """The start method ``context=None`` stands for: ``"fork"`` on Linux, else ``"spawn"``."""
    return "fork" if sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods() else "spawn"


class _Pickled:
    """Carries an env function (often a lambda or closure) to a spawned worker with cloudpickle."""

    def __init__(self, payload: Any) -> None:
        self.payload = payload

    def __getstate__(self) -> bytes:
        return cloudpickle.dumps(self.payload)

    def __setstate__(self, state: bytes) -> None:
        self.payload = cloudpickle.loads(state)


def _worker(index: int, env_fn: _Pickled, pipe, parent_pipe) -> None:
    """A worker process: builds one env and serves the parent's commands until ``close``.

    Each reply is ``(result, True)``, or ``((error type name, message, traceback), False)``.
    """
    parent_pipe.close()
    env = None
    try:
        env = env_fn.payload()
        while True:
            command, data = pipe.recv()
            try:
                if command == "spaces":
                    result = (env.observation_space, env.action_space, env.metadata,
                              getattr(env, "render_mode", None), getattr(env, "spec", None))
                elif command == "reset":
                    result = env.reset(**data)
                elif command == "step":
                    result = autoreset_step(env, data)
                elif command == "render":
                    result = env.render()
                elif command == "call":
                    name, args, kwargs = data
                    attribute = wrapper_attr(env, name)
                    result = attribute(*args, **kwargs) if callable(attribute) else attribute
                elif command == "setattr":
                    set_wrapper_attr(env, *data)
                    result = None
                elif command == "close":
                    pipe.send((None, True))
                    break
                else:
                    raise RuntimeError(f"unknown command {command!r}")
            except Exception as error:  # noqa: BLE001 - reported to the parent, which raises it
                pipe.send(((type(error).__name__, str(error), traceback.format_exc()), False))
            else:
                pipe.send((result, True))
    except (KeyboardInterrupt, EOFError):
        pass
    except Exception as error:  # noqa: BLE001 - the env could not be built: tell the parent
        pipe.send(((type(error).__name__, str(error), traceback.format_exc()), False))
    finally:
        if env is not None:
            env.close()


class WorkerError(RuntimeError):
    """An env in a worker process raised; the message holds its error and traceback."""


class SafetyAsyncVectorEnv(SafeVectorEnv):
    """Vector env of the envs ``env_fns`` build, each in its own process (the API of :class:`SafeVectorEnv`).

    Args:
        env_fns: callables that each build one env with Safety-Gymnasium's 6-tuple ``step`` (lambdas
            and closures are fine: they travel with cloudpickle).
        observation_space / action_space: one env's spaces (default: the first env's).
        shared_memory: accepted for the original's signature; observations travel through the pipes.
        copy: accepted for the original's signature (observations are always fresh arrays here).
        context: the multiprocessing start method (module docstring); ``None``: :func:`default_context`.
        daemon: whether the workers are daemon processes (killed with this one).
        worker: a custom worker target with :func:`_worker`'s signature and protocol.

    Raises:
        WorkerError: an env raised in its worker (also at construction, if it could not be built).
    """

    def __init__(self, env_fns: Sequence[Callable[[], gymnasium.Env]], observation_space: gymnasium.Space | None = None,
                 action_space: gymnasium.Space | None = None, shared_memory: bool = True, copy: bool = True,
                 context: str | None = None, daemon: bool = True, worker: Callable | None = None) -> None:
        env_fns = list(env_fns)
        if not env_fns:
            raise ValueError("SafetyAsyncVectorEnv needs at least one env function")
        self.context = context or default_context()
        ctx = mp.get_context(self.context)
        self.parent_pipes, self.processes = [], []
        self.closed = True  # until the workers run, close() has nothing to do
        for index, env_fn in enumerate(env_fns):
            parent_pipe, child_pipe = ctx.Pipe()
            process = ctx.Process(target=worker or _worker, name=f"SafetyAsyncVectorEnv-{index}",
                                  args=(index, _Pickled(env_fn), child_pipe, parent_pipe), daemon=daemon)
            self.parent_pipes.append(parent_pipe)
            self.processes.append(process)
            process.start()
            child_pipe.close()
        self.closed = False
        try:
            spaces = self._receive([self._send(0, "spaces", None)])[0]
        except BaseException:
            self.close()
            raise
        first_obs_space, first_act_space, metadata, render_mode, spec = spaces
        self._setup(len(env_fns), observation_space or first_obs_space, action_space or first_act_space,
                    metadata, render_mode, spec, copy)

    # ------------------------------------------------------------------ pipes
    def _send(self, index: int, command: str, data: Any) -> int:
        self.parent_pipes[index].send((command, data))
        return index

    def _receive(self, indices: list[int]) -> list[Any]:
        results, errors = [], []
        for index in indices:
            try:
                result, ok = self.parent_pipes[index].recv()
            except EOFError:
                result, ok = ("EOFError", "the worker process died", ""), False
            if not ok:
                errors.append(f"env {index}: {result[0]}: {result[1]}\n{result[2]}")
            results.append(result)
        if errors:
            raise WorkerError("\n".join(errors))
        return results

    def _all(self, command: str, data: list[Any]) -> list[Any]:
        return self._receive([self._send(index, command, value) for index, value in enumerate(data)])

    # ------------------------------------------------------------------ SafeVectorEnv hooks
    def _reset_envs(self, seeds: list[int | None], options: dict | None) -> list[tuple[Any, dict]]:
        return self._all("reset", [{"seed": seed, **({} if options is None else {"options": options})}
                                   for seed in seeds])

    def _step_envs(self, actions: list[Any]) -> list[tuple]:
        return self._all("step", actions)

    def _images(self) -> list[Any]:
        return self._all("render", [None] * self.num_envs)

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        """Call method ``name`` of every env (or read attribute ``name``): a tuple of the results."""
        self._check_open()
        return tuple(self._all("call", [(name, args, kwargs)] * self.num_envs))

    def _set_attrs(self, name: str, values: list[Any]) -> None:
        self._all("setattr", [(name, value) for value in values])

    def _close_envs(self) -> None:
        for index, process in enumerate(self.processes):
            if process.is_alive():
                try:
                    self._send(index, "close", None)
                    self.parent_pipes[index].recv()
                except (BrokenPipeError, EOFError, OSError):
                    pass
        for process in self.processes:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()
        for pipe in self.parent_pipes:
            pipe.close()

    def __del__(self) -> None:
        if not getattr(self, "closed", True):
            self.close()
