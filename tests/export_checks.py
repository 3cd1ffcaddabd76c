"""Run ``torch.export`` programs in a clean interpreter in which sg_torchrl, TorchRL and tensordict cannot be
imported: what an exported policy promises (it needs torch alone)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import torch

_LOAD_WITHOUT_SG_TORCHRL = textwrap.dedent("""
    import sys
    for name in ("sg_torchrl", "torchrl", "tensordict"):
        sys.modules[name] = None  # importing them now fails, so loading cannot use them
    try:
        import sg_torchrl
    except ImportError:
        pass
    else:
        raise SystemExit("sg_torchrl is importable")
    import torch
    arguments = sys.argv[1:]
    for program, observations, out in zip(arguments[::3], arguments[1::3], arguments[2::3]):
        policy = torch.export.load(program).module()
        with torch.no_grad():
            actions = policy(torch.load(observations, weights_only=True))
        torch.save(actions, out)
    loaded = [n for n, m in sys.modules.items() if m is not None and n.split(".")[0] in ("sg_torchrl", "torchrl", "tensordict")]
    assert not loaded, loaded
""")


def run_exported(programs: list[tuple[Path, torch.Tensor]], workdir: Path) -> list[torch.Tensor]:
    """Each program's actions on its observations, computed in one clean subprocess (``python -I``)."""
    arguments = []
    for k, (program, observations) in enumerate(programs):
        torch.save(observations, workdir / f"obs-{k}.pt")
        arguments += [str(program), str(workdir / f"obs-{k}.pt"), str(workdir / f"actions-{k}.pt")]
    result = subprocess.run([sys.executable, "-I", "-c", _LOAD_WITHOUT_SG_TORCHRL, *arguments], cwd=workdir,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return [torch.load(workdir / f"actions-{k}.pt", weights_only=True) for k in range(len(programs))]
