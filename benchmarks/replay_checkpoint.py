"""What one checkpoint of a seed group's replay buffers writes, and how long it takes.

S = 3 SafetyHalfCheetahVelocity-v1 buffers (a row: 17 + 6 + 1 + 1 + 1 + 17 float32, 172 bytes) of capacity
``--capacity`` (OmniSafe's 1,000,000), filled with ``--fill`` rows per seed, checkpointed, then ``--since``
more rows per seed written (a minute of collection), then the measured checkpoint (the median of
``--repeats`` such rounds). The replay code is whichever ``sg_torchrl`` is on the path, so the same script
measures a revision before and after a change:

* a revision whose ``SeedReplay`` has ``dump``: every checkpoint dumps each whole storage with TorchRL's
  ``ReplayBuffer.dumps`` (then removes the older dump);
* one with ``checkpoint`` / ``commit``: the live memory maps are flushed (the pages written since the last
  checkpoint) and the rows overwritten after a wrap-around are kept in undo files.

Reported per checkpoint interval (the rows since, then the checkpoint): the checkpoint's wall seconds (the
incremental one's ``fsync`` of the pages the rows since dirtied included), the seconds writing the rows
(the incremental checkpoints' undo files are written there, ahead of the writer), and the bytes the process
wrote in the interval by the kernel's count (``/proc/self/io`` ``write_bytes``, the bytes dirtied: the rows
themselves, 1,000 x 172 B x 3 = 0.5 MB here, plus the dumps, or the undo files and metadata).
``--capacity 20000 --fill 25000`` measures a buffer that has wrapped, where every row written overwrites
one the last checkpoint holds.

    PYTHONPATH=. python benchmarks/replay_checkpoint.py              # this revision
    PYTHONPATH=/path/to/older python benchmarks/replay_checkpoint.py # another one
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch

from _report import write_json
from sg_torchrl.train.replay import SeedReplay

OBS, ACT = 17, 6


def written_bytes() -> int:
    with open("/proc/self/io") as handle:
        return next(int(line.split()[1]) for line in handle if line.startswith("write_bytes"))


def fill(replay: SeedReplay, rows: int, generator: torch.Generator, chunk: int = 1000) -> None:
    seeds = len(replay.seeds)
    for start in range(0, rows, chunk):
        n = min(chunk, rows - start)
        f = lambda k: torch.randn(seeds, n, k, generator=generator)  # noqa: E731
        replay.extend(f(OBS), f(ACT), f(1), f(1), f(1) > 0, f(OBS))


def checkpoint(replay: SeedReplay, epoch: int) -> None:
    if hasattr(replay, "dump"):  # the full dumps
        replay.prune(replay.dump(epoch))
    else:
        replay.checkpoint(epoch)
        replay.commit()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--capacity", type=int, default=1_000_000)
    parser.add_argument("--fill", type=int, default=20_000)
    parser.add_argument("--since", type=int, default=1_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(0)
    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as tmp:
        run = Path(tmp)
        replay = SeedReplay(run, list(range(args.seeds)), [torch.Generator().manual_seed(s) for s in range(args.seeds)],
                            capacity=args.capacity, batch_size=256, obs_dim=OBS, action_dim=ACT)
        fill(replay, args.fill, generator)
        checkpoint(replay, 1)
        seconds, rows_seconds, written = [], [], []
        for epoch in range(2, 2 + args.repeats):
            before, start = written_bytes(), time.perf_counter()
            fill(replay, args.since, generator)
            middle = time.perf_counter()
            checkpoint(replay, epoch)
            seconds.append(time.perf_counter() - middle)
            rows_seconds.append(middle - start)
            written.append(written_bytes() - before)
    method = "full dump" if hasattr(SeedReplay, "dump") else "incremental"
    row = {"method": method, "seeds": args.seeds, "capacity": args.capacity, "fill": args.fill, "since": args.since,
           "seconds": statistics.median(seconds), "rows_seconds": statistics.median(rows_seconds),
           "write_bytes": statistics.median(written)}
    print("| method | seeds | capacity | rows per seed | rows since | s per checkpoint | s writing the rows | "
          "MB written per interval |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| {method} | {args.seeds} | {args.capacity:,} | {args.fill:,} | {args.since:,} | {row['seconds']:.3f} | "
          f"{row['rows_seconds']:.3f} | {row['write_bytes'] / 1e6:.2f} |")
    if args.json:
        write_json(args.json, [row], threads=1)


if __name__ == "__main__":
    main()
