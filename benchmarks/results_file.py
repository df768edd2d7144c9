"""The benchmarks' JSON output (``--json-out FILE``): the figures of one run, the command and the machine.

``benchmarks/write_table.py`` turns these files (``benchmarks/results/*.json``) into ``docs/benchmarks.md``.

    {"benchmark": "bench_sim.py", "command": "python benchmarks/bench_sim.py --runs 3",
     "machine": {"cpu": "AMD EPYC ...", "cores": 2, "load": 1.3, "date": "2026-11-28"},
     "figures": {"sim.frames_per_s": 41.2, ...}}
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import shlex
import sys
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else what the platform module says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine() -> dict:
    """CPU model, cores this process may use, the 1-minute load average at the end of the run
    (other processes on a shared machine slow CPU and wall times), and the UTC date."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    out = {"cpu": cpu_model(), "cores": cores, "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d")}
    try:
        out["load"] = round(os.getloadavg()[0], 1)
    except (AttributeError, OSError):
        pass
    return out


def command_line(argv: list[str] | None = None) -> str:
    """The command that produced the figures, without its ``--json-out`` option."""
    argv = list(sys.argv if argv is None else argv)
    out, skip = [], False
    for a in argv[1:]:
        if skip:
            skip = False
            continue
        if a == "--json-out":
            skip = True
            continue
        if a.startswith("--json-out="):
            continue
        out.append(a)
    script = Path(argv[0])
    name = f"benchmarks/{script.name}" if script.parent.name == "benchmarks" else str(script)
    return " ".join(["python", name, *map(shlex.quote, out)])


def write_results(path: str | Path, benchmark: str, figures: dict[str, float | int | None]) -> None:
    """Write one run's figures (``None`` values are left out: a figure not measured is no row)."""
    data = {"benchmark": benchmark, "command": command_line(), "machine": machine(),
            "figures": {k: v for k, v in figures.items() if v is not None}}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    print(f"wrote {p}")
