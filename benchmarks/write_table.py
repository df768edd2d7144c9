"""Write ``docs/benchmarks.md`` from the benchmarks' JSON output (``benchmarks/results/*.json``).

One row per figure: what it is, its latest value, its target, whether the value meets it, the
command that measured it and the machine it ran on.  Labels, units and targets live in ``FIGURES``
below; a figure in the JSON that ``FIGURES`` does not name is still a row (named by its key, no
target).  Refresh the JSON with the benchmarks' ``--json-out``, then:

    python benchmarks/write_table.py [--results benchmarks/results] [--out docs/benchmarks.md] [--check]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Figure:
    label: str
    unit: str = ""                           # shown after the value
    scale: float = 1.0                       # shown value = JSON value x scale (m -> mm: 1000)
    digits: int = 2                          # decimals shown
    target: tuple[str, float] | None = None  # (">=" or "<=", bound in the shown unit)


def _peer_case(case: str, what: str, end_pct: float | None, lost_ok: bool = False, ate_mm: float | None = None,
               median_ms: float | None = None, p95_ms: float | None = None) -> dict[str, Figure]:
    """The rows of one bench_peers case; targets of the estimator's issues (ATE <= 0.9x ORB-SLAM3's, end
    error and CPU per frame <= ORB-SLAM3's, an end error bound; the subsampled cases lose no frame)."""
    def bound(v):
        return None if v is None else ("<=", v)

    k = f"peers.{case}"
    return {
        f"{k}.ate_ratio": Figure(f"{what}: ATE, ours / ORB-SLAM3 (same run)", "x", target=("<=", 0.9)),
        f"{k}.end_error_ratio": Figure(f"{what}: end-point error, ours / ORB-SLAM3 (same run)", "x",
                                       target=("<=", 1.0)),
        f"{k}.cpu_ratio": Figure(f"{what}: CPU per frame, ours / ORB-SLAM3 (same run)", "x", target=("<=", 1.0)),
        f"{k}.end_error_pct": Figure(f"{what}: end-point error, ours", "% of path", digits=3, target=bound(end_pct)),
        f"{k}.ate_m": Figure(f"{what}: ATE RMSE, ours", "mm", scale=1000.0, target=bound(ate_mm)),
        f"{k}.cpu_ms": Figure(f"{what}: CPU per frame (all threads), ours", "ms", digits=1),
        f"{k}.cpu_live_ms": Figure(f"{what}: CPU per frame without image decoding, ours", "ms", digits=1),
        f"{k}.cpu_command_ms": Figure(f"{what}: CPU per frame of the whole `stereopath odometry` command", "ms",
                                      digits=1),
        f"{k}.median_ms": Figure(f"{what}: estimator wall time per frame, median", "ms", digits=1,
                                 target=bound(median_ms)),
        f"{k}.p95_ms": Figure(f"{what}: estimator wall time per frame, p95", "ms", digits=1, target=bound(p95_ms)),
        f"{k}.frames_lost": Figure(f"{what}: frames lost", "", digits=0, target=("<=", 0) if lost_ok else None),
    }


def _peer_score() -> dict[str, Figure]:
    """The score line of ``bench_peers.py --all``: geometric means and worst cases of ours / ORB-SLAM3."""
    out = {}
    for key, what in (("ate", "ATE"), ("end_error", "end-point error"), ("cpu", "CPU per frame")):
        out[f"peers.score.{key}_gmean"] = Figure(f"all cases: {what}, ours / ORB-SLAM3, geometric mean", "x")
        out[f"peers.score.{key}_worst"] = Figure(f"all cases: {what}, ours / ORB-SLAM3, worst case", "x",
                                                 target=("<=", 0.9 if key == "ate" else 1.0))
    return out


# Every figure the table knows, in the table's order.
FIGURES: dict[str, Figure] = {
    **_peer_case("kitti06", "KITTI 06 frames 0-50", 1.0),
    **_peer_case("kitti06_s2", "KITTI 06 0-50, every 2nd frame", 2.0, lost_ok=True),
    **_peer_case("kitti06_s3", "KITTI 06 0-50, every 3rd frame", 2.0, lost_ok=True),
    **_peer_case("euroc", "EuRoC V1_01, first 95 frames", None),
    **_peer_case("sim", "simulated scan (400 frames)", 0.05, ate_mm=1.0, median_ms=25.0, p95_ms=50.0),
    **_peer_case("sim_handheld", "simulated hand-held scan (400 frames, started in motion)", None),
    **_peer_score(),
    "features.graf.1to4.fast.correct": Figure("graffiti 1->4: correct matches, `fast`", "", digits=0,
                                              target=(">=", 1000)),
    "features.graf.1to4.fast.cpu_share_of_full": Figure("graffiti 1->4: CPU time, `fast` / OpenCV ASIFT (same run)",
                                                        "%", scale=100.0, digits=1, target=("<=", 20.0)),
    "features.graf.1to5.fast.correct_vs_sift": Figure("graffiti 1->5: correct matches, `fast` / SIFT", "x",
                                                      digits=1, target=(">=", 3.0)),
    "features.graf.1to6.fast.correct_vs_sift": Figure("graffiti 1->6: correct matches, `fast` / SIFT", "x",
                                                      digits=1, target=(">=", 3.0)),
    "features.graf.1to4.sift.correct": Figure("graffiti 1->4: correct matches, SIFT", "", digits=0),
    "features.graf.1to5.sift.correct": Figure("graffiti 1->5: correct matches, SIFT", "", digits=0),
    "features.graf.1to6.sift.correct": Figure("graffiti 1->6: correct matches, SIFT", "", digits=0),
    "features.graf.1to5.fast.correct": Figure("graffiti 1->5: correct matches, `fast`", "", digits=0),
    "features.graf.1to6.fast.correct": Figure("graffiti 1->6: correct matches, `fast`", "", digits=0),
    "sim.frames_per_s": Figure("simulator: stereo frames per second, 640x480", "/s", digits=1, target=(">=", 30.0)),
    "sim.cpu_ms_per_frame": Figure("simulator: CPU per stereo frame", "ms", digits=1),
    "sim.motion_blur_frames_per_s": Figure("simulator with motion blur: stereo frames per second", "/s", digits=1),
    "reprocess.sim.ate_onboard_m": Figure("reprocess, simulated scan: ATE on board (`stereo`)", "mm", scale=1000.0),
    "reprocess.sim.ate_after_m": Figure("reprocess, simulated scan: ATE after bundle adjustment (GTSAM + IMU)", "mm",
                                        scale=1000.0),
    "reprocess.sim.ate_ratio": Figure("reprocess, simulated scan: ATE after / on board", "x", target=("<=", 0.8)),
    "reprocess.sim.end_to_end_s": Figure("reprocess, simulated scan: `host reprocess` end to end (wall)", "s",
                                         digits=0, target=("<=", 180.0)),
}

HEADER = """# Benchmarks

<!-- Written by benchmarks/write_table.py from benchmarks/results/*.json: edit those, not this page. -->

One row per figure: the latest value measured, its target, the command that measured it and the
machine (with its 1-minute load average when the run ended). CPU and wall times depend on the
machine and on what else runs on it; ratios against ORB-SLAM3 or OpenCV's ASIFT are taken in the
same run, so they compare across machines better than the times themselves. Refresh a row by
running its command with `--json-out benchmarks/results/NAME.json`, then
`python benchmarks/write_table.py`.

"""


class ResultsError(ValueError):
    """A results file that is not what the benchmarks write."""


def load_results(folder: Path) -> list[dict]:
    """Every ``*.json`` in ``folder``, checked, in file-name order."""
    runs = []
    for path in sorted(Path(folder).glob("*.json")):
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ResultsError(f"{path}: not readable JSON ({exc})") from None
        if not isinstance(data, dict):
            raise ResultsError(f"{path}: expected an object with benchmark, command, machine, figures")
        missing = [k for k in ("benchmark", "command", "machine", "figures") if k not in data]
        if missing:
            raise ResultsError(f"{path}: missing {', '.join(missing)}")
        machine = data["machine"]
        if not isinstance(machine, dict) or any(k not in machine for k in ("cpu", "cores", "date")):
            raise ResultsError(f"{path}: machine needs cpu, cores and date")
        figures = data["figures"]
        if not isinstance(figures, dict):
            raise ResultsError(f"{path}: figures must be an object of name: number")
        for name, value in figures.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ResultsError(f"{path}: figure {name!r} is {value!r}, not a number")
        runs.append(dict(data, file=path.name))
    return runs


def fmt_value(fig: Figure, value: float) -> str:
    v = value * fig.scale
    text = f"{v:,.{fig.digits}f}"
    if not fig.unit:
        return text
    return f"{text}{fig.unit}" if fig.unit in ("x", "%", "/s") else f"{text} {fig.unit}"


def fmt_target(fig: Figure) -> str:
    if fig.target is None:
        return ""
    op, bound = fig.target
    return f"{'≤' if op == '<=' else '≥'} {fmt_value(fig, bound / fig.scale)}"


def meets(fig: Figure, value: float) -> str:
    if fig.target is None:
        return ""
    op, bound = fig.target
    shown = value * fig.scale
    ok = shown <= bound if op == "<=" else shown >= bound
    return "yes" if ok else "**no**"


def rows(runs: list[dict]) -> list[tuple[str, str, str, str, str, str]]:
    """(figure, value, target, met, command, machine), known figures in FIGURES' order, then the rest."""
    order = {k: i for i, k in enumerate(FIGURES)}
    entries = []
    for run in runs:
        m = run["machine"]
        load = f", load {m['load']}" if "load" in m else ""
        machine = f"{m['cpu']}, {m['cores']} cores{load}, {m['date']}"
        for name, value in run["figures"].items():
            fig = FIGURES.get(name, Figure(f"`{name}`", digits=4))
            entries.append(((order.get(name, len(order)), name),
                            (fig.label, fmt_value(fig, value), fmt_target(fig), meets(fig, value),
                             f"`{run['command']}`", machine)))
    entries.sort(key=lambda e: e[0])
    return [e[1] for e in entries]


def render(folder: Path) -> str:
    runs = load_results(folder)
    lines = [HEADER.rstrip("\n"), ""]
    if not runs:
        lines.append(f"No results yet: no JSON files in `{folder.name}/`.")
        return "\n".join(lines) + "\n"
    lines.append("| figure | latest | target | met | command | machine |")
    lines.append("|---|---|---|---|---|---|")
    for row in rows(runs):
        lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default=str(ROOT / "benchmarks" / "results"), help="folder of the JSON files")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks.md"))
    ap.add_argument("--check", action="store_true", help="only compare: exit 1 when --out differs from the JSON")
    args = ap.parse_args(argv)
    try:
        text = render(Path(args.results))
    except ResultsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if args.check:
        current = out.read_text(encoding="utf-8") if out.is_file() else None
        if current != text:
            print(f"{out} is not what {args.results} gives; run python benchmarks/write_table.py", file=sys.stderr)
            return 1
        return 0
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
