"""Where training's resident memory peaks: the default cube model trained on tiled records while a thread samples
the resident set and prints the running Python stack at each new high.

Paper, Experimental Setup (training from many simulated pushes). The records of one run (``BASE``, a
``pushtorch-simulate`` run folder or its ``pushes/``) are tiled to ``PUSHES`` as ``tools/bench_scale.py`` tiles
them. Run it with ``MALLOC_MMAP_THRESHOLD_=65536`` in the environment to see how much of the peak is glibc's heap
keeping freed blocks (large blocks then go to mmap and back to the system when freed).

    .venv/bin/python tools/profile_train_memory.py BASE [PUSHES]

The last line is ``peak_mb=<..>``.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
import traceback
from dataclasses import replace

import torch

from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.parallel import resident_mb
from pushtorch.sim import load_records
from pushtorch.sim.records import PushRecords


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", help="a simulation run folder of cube pushes")
    parser.add_argument("pushes", type=int, nargs="?", default=20_000)
    args = parser.parse_args()
    one = load_records(args.base, trajectories=False)
    copies = -(-args.pushes // len(one))
    records = PushRecords.cat([replace(one, index=one.index + k * len(one)) for k in range(copies)])
    records = records.take(torch.arange(args.pushes))
    main_thread, best = threading.main_thread().ident, [0.0]

    def watch() -> None:
        while True:
            now = resident_mb()
            if now > best[0] + 20:
                best[0] = now
                stack = "".join(traceback.format_stack(sys._current_frames()[main_thread])[-5:])
                print(f"--- {now:.0f} MB\n{stack}", flush=True)
            time.sleep(0.2)

    threading.Thread(target=watch, daemon=True).start()
    train_push_model(load_object("cube"), records, generator=0)
    print(f"peak_mb={max(best[0], resident_mb()):.0f}")


if __name__ == "__main__":
    main()
