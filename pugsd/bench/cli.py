# SPDX-License-Identifier: Apache-2.0
"""``pugsd bench [--json PATH] [--quick]``: the benchmark (also ``tools/bench``)."""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
from pathlib import Path
from typing import Any


def _finite(obj: Any) -> Any:
    """Strict JSON: NaN and infinities become null."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _bench(args: argparse.Namespace) -> int:
    from pugsd.bench.options import BenchOptions
    from pugsd.bench.run import run_bench
    from pugsd.bench.targets import format_table

    opts = BenchOptions.quick_preset() if args.quick else BenchOptions.full()
    if args.no_daemon and args.no_pipeline:
        sys.stderr.write("pugsd bench: --no-daemon and --no-pipeline leave nothing to measure\n")
        return 2
    if args.no_daemon:
        opts = opts.replace(use_daemon=False)
    if args.no_pipeline:
        opts = opts.replace(use_pipeline=False)

    from pugsd.progress import progress_bar, ticking

    # in the sections' typical seconds (pugsd.bench.run.section_weights): the ETA follows the
    # pace observed so far
    bar = progress_bar(None, "bench", unit=" s")
    bar.bar_format = "{desc} {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]"

    def write(line: str) -> None:
        bar.clear()  # the bar on stderr, the report on stdout: one terminal
        sys.stdout.write(line + "\n")
        sys.stdout.flush()
        if line:
            bar.set_description_str(f"bench: {line[:50]}", refresh=False)

    def progress(done: float, total: float) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    argv = sys.argv[1:] if "bench" in sys.argv[1:] else ["bench", *sys.argv[1:]]
    command = " ".join(shlex.quote(a) for a in ["pugsd", *argv])
    with ticking(bar):
        result = run_bench(opts, args.set or (), args.device, write, command, args.torch_threads, progress)
    write("")
    table = format_table(result)
    for line in table:
        write(line)
    result["table"] = table
    if args.json:
        path = Path(args.json)
        if path.parent and not path.parent.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(_finite(result), indent=2, allow_nan=False, default=str) + "\n")
        os.replace(tmp, path)
        write(f"wrote {path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "bench",
        help="measure latency, throughput, memory and paper-vs-streaming on synthetic stereo",
        description=(
            "Synthetic 640x480 stereo at 10 Hz (complete and partial trajectories): per-stage "
            "latency, sustained throughput and a long replay through the in-process daemon, and "
            "the paper's batch pipeline against streaming on the same frames. --quick finishes "
            "in about a minute and is not comparable with the targets."
        ),
        epilog="example:\n  pugsd bench --quick --json bench-results.json",
    )
    p.add_argument("--json", metavar="PATH", help="also write the results as JSON (default: not written)")
    p.add_argument("--quick", action="store_true", help="a short smoke run (< 1 min)")
    p.add_argument(
        "--device", default="auto", choices=("auto", "cpu", "cuda"),
        help="SVGP device (auto: CUDA when present)",
    )  # fmt: skip
    p.add_argument(
        "--torch-threads", type=int, default=None, metavar="N",
        help="torch.set_num_threads(N) before measuring (default: the config's "
        "[daemon] torch_threads, as the daemon does; 0 keeps torch's own choice)",
    )  # fmt: skip
    p.add_argument(
        "--no-daemon", action="store_true",
        help="skip the daemon-based throughput and long-replay measurements",
    )  # fmt: skip
    p.add_argument(
        "--no-pipeline", action="store_true",
        help="skip the per-trajectory pipeline measurements (stage latencies, paper vs "
        "streaming); the daemon sections then run alone, without the paper fit to agree with",
    )  # fmt: skip
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override")
    p.set_defaults(func=_bench)
