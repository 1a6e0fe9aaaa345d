"""Where a trained run's training steps spend their time, on the CPU or a GPU (issue 13).

Continues a finished run (a copy of its checkpoint, in a temporary folder) for ``--steps`` more
iterations at its final grid: the first half timed plainly (ms per step, from the
training loop's own clock in the checkpoint, so loading the data and saving are not counted), the second half under ``torch.profiler``, whose table of operators
(sorted by their own time on the device: the GPU's kernels under CUDA, the CPU's otherwise) is
printed. The run's own settings are kept; only the iteration count grows (its learning-rate
schedule is stretched over the longer run, which does not change the work per step).

``--count N`` adds N more steps under a dispatch-mode counter (``HostCounter``) and prints, per
step: the operators dispatched, the host reads of tensor values (``.item()``, ``float()``,
``bool()``, ``nonzero``, boolean-mask indexing: on a GPU each waits for the device to finish
what was queued) and the tensors made from host data (``torch.tensor``, ``new_tensor``, a copy
from the CPU to another device: on a GPU each is a host-to-device transfer), each with the
lines of the trainer that make them. These are counts, the same on any machine; the same code
makes them on a GPU, so they can be read on the CPU. On the CPU they include the backward's
operators; on a GPU autograd runs the backward on a thread of its own, which the counter does
not see.

    python bench/bench_trainer_profile.py RUN [--steps 200] [--device cuda] [--rows 25] [--count 10]
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import shutil
import tempfile
import traceback
import weakref
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from spikegen.errors import InputError
from spikenerf.config import TrainConfig
from spikenerf.train import train


def _checkpoint(out: Path) -> dict:
    return torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)


def continue_run(out: Path, cfg: TrainConfig, until: int) -> None:
    """Train the copy in ``out`` on to iteration ``until``."""
    train(dataclasses.replace(cfg, iters=until), out, progress=False, log=lambda m: None)


# operators that read a tensor's values on the host: on a GPU each waits for the device (a sync)
_HOST_READS = {"aten._local_scalar_dense.default", "aten.nonzero.default", "aten.masked_select.default",
               "aten.is_nonzero.default", "aten.equal.default"}


class HostCounter(TorchDispatchMode):
    """Counts dispatched operators, host reads of tensor values and tensors made from host data,
    the last two by the trainer's line that makes them (``sites``)."""

    def __init__(self):
        super().__init__()
        self.ops = 0
        self.reads = collections.Counter()
        self.uploads = collections.Counter()
        # tensors drawn from a torch.Generator or made from such alone (``int(draw)`` reads a
        # detached alias), by id (an entry goes when its tensor does, so no id is mistaken): the
        # trainer's generators are on the CPU on every device, so reading these costs no wait (not counted)
        self.drawn = weakref.WeakValueDictionary()

    def __enter__(self):
        # Tensor.tolist reads the values without dispatching an operator on the CPU: counted here
        self._tolist = torch.Tensor.tolist
        counter, tolist = self, self._tolist

        def counted(t, *a, **k):
            if id(t) not in counter.drawn:
                counter.reads[counter._site()] += 1
            return tolist(t, *a, **k)
        torch.Tensor.tolist = counted
        return super().__enter__()

    def __exit__(self, *exc):
        torch.Tensor.tolist = self._tolist
        return super().__exit__(*exc)

    @staticmethod
    def _site() -> str:
        frames = [f for f in traceback.extract_stack() if "spikenerf" in f.filename or "spikegen" in f.filename]
        return f"{Path(frames[-1].filename).name}:{frames[-1].lineno} {frames[-1].name}" if frames else "(other)"

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.ops += 1
        name = str(func)
        bool_index = name.startswith("aten.index") and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for a in args[1:2] if isinstance(a, (list, tuple))
            for i in a)
        if (name in _HOST_READS or bool_index) and not (args and isinstance(args[0], torch.Tensor)
                                                         and id(args[0]) in self.drawn):
            self.reads[self._site()] += 1
        out = func(*args, **kwargs)
        inputs = [a for a in args if isinstance(a, torch.Tensor)]
        if isinstance(out, torch.Tensor) and (kwargs.get("generator") is not None or (
                inputs and all(id(a) in self.drawn for a in inputs))):  # a draw, or made from draws alone
            self.drawn[id(out)] = out
        if name == "aten.lift_fresh.default" or (
                name in ("aten._to_copy.default", "aten.copy_.default") and isinstance(out, torch.Tensor)
                and out.device.type != "cpu" and any(isinstance(a, torch.Tensor) and a.device.type == "cpu"
                                                     for a in args)):
            self.uploads[self._site()] += 1
        return out


def count_host_work(out: Path, cfg: TrainConfig, start: int, steps: int) -> None:
    """Print what :class:`HostCounter` sees per step over ``steps`` steps from ``start``."""
    counter = HostCounter()
    with counter:
        continue_run(out, cfg, start + steps)
    print(f"per step over {steps} steps: {counter.ops / steps:.1f} operators dispatched, "
          f"{sum(counter.reads.values()) / steps:.1f} host reads of tensor values, "
          f"{sum(counter.uploads.values()) / steps:.1f} tensors from host data")
    for title, table in (("host reads", counter.reads), ("tensors from host data", counter.uploads)):
        for site, n in table.most_common():
            print(f"  {title:>22}  {n / steps:5.1f}  {site}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a finished spikenerf run folder (config.json + checkpoint.pt)")
    ap.add_argument("--steps", type=int, default=200, help="iterations to add: half timed, half profiled")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--rows", type=int, default=25, help="operators in the table")
    ap.add_argument("--count", type=int, default=0, help="steps more under the host-work counter (0: none)")
    args = ap.parse_args()
    missing = [n for n in ("config.json", "checkpoint.pt") if not (args.run / n).is_file()]
    if missing:
        ap.exit(2, f"bench_trainer_profile.py: {args.run} is not a trained run (no {' or '.join(missing)})\n")
    if args.steps < 2 or args.rows < 1 or args.count < 0:
        ap.exit(2, "bench_trainer_profile.py: --steps must be at least 2, --rows at least 1, --count at least 0\n")
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.exit(2, "bench_trainer_profile.py: --device cuda asked for, but this machine has no CUDA GPU\n")
    saved = json.loads((args.run / "config.json").read_text())
    keys = {f.name for f in dataclasses.fields(TrainConfig)}
    # the settings the checkpoint was trained with win over config.json's; a run from before early ray
    # termination or the sRGB weight trained without them (the trainer's own reading of such a checkpoint)
    ck = _checkpoint(args.run)
    made = {"stop_transmittance": 0.0, "srgb_weight": 0.0, **ck["config"]}
    cfg = TrainConfig(**{k: v for k, v in {**saved, **made}.items() if k in keys})
    cfg = dataclasses.replace(cfg, device=args.device, checkpoint_every_s=1e9, checkpoint_every=10 ** 9)
    done = int(ck["iteration"])
    del ck
    half = max(args.steps // 2, 1)
    print(f"{args.run} ({cfg.method}, {saved['width']} x {saved['height']}, trained {done} iterations); device "
          f"{args.device}" + (f" ({torch.cuda.get_device_name()})" if args.device == "cuda" else "") +
          f"; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; torch threads {torch.get_num_threads()}")
    with tempfile.TemporaryDirectory(prefix="bench_profile_") as tmp:
        out = Path(tmp) / "run"
        out.mkdir()
        shutil.copy2(args.run / "checkpoint.pt", out / "checkpoint.pt")
        # a few steps first: the CUDA context, kernels and allocator warm up outside what is timed
        continue_run(out, cfg, done + 5)
        # the training loop's own clock (train_seconds), before and after: loading the data and saving are not in it
        before = float(_checkpoint(out)["train_seconds"])
        continue_run(out, cfg, done + 5 + half)
        loop = float(_checkpoint(out)["train_seconds"]) - before
        print(f"{half} steps at the final grid: {1000 * loop / half:.1f} ms per step ({loop:.2f} s in the training "
              f"loop; loading the data and the checkpoint are not counted)")
        acts = [torch.profiler.ProfilerActivity.CPU]
        if args.device == "cuda":
            acts.append(torch.profiler.ProfilerActivity.CUDA)
        with torch.profiler.profile(activities=acts) as prof:
            continue_run(out, cfg, done + 5 + 2 * half)
        if args.count:
            count_host_work(out, cfg, done + 5 + 2 * half, args.count)
    key = "self_cuda_time_total" if args.device == "cuda" else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=args.rows))


if __name__ == "__main__":
    try:
        main()
    except InputError as e:  # a run the trainer cannot continue: its one line
        raise SystemExit(f"bench_trainer_profile.py: {e}")
