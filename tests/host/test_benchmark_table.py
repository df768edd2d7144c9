"""benchmarks/write_table.py: the benchmarks' JSON -> docs/benchmarks.md, one row per figure."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _load(name: str):
    """benchmarks/<name>.py as a module (registered, as dataclasses need)."""
    key = f"_benchmarks_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, ROOT / "benchmarks" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[key] = mod
        spec.loader.exec_module(mod)
    return sys.modules[key]


@pytest.fixture(scope="module")
def wt():
    return _load("write_table")


def _write(folder: Path, name: str, data) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps(data))


MACHINE = {"cpu": "Test CPU 3000", "cores": 2, "date": "2026-01-02"}


def test_fixture_becomes_the_expected_table(wt, tmp_path):
    res = tmp_path / "results"
    _write(res, "peers.json", {"benchmark": "bench_peers.py", "command": "python benchmarks/bench_peers.py --cases kitti06",
                               "machine": MACHINE,
                               "figures": {"peers.kitti06.cpu_ratio": 1.234, "peers.kitti06.ate_ratio": 0.8512,
                                           "peers.kitti06.ate_m": 0.0341}})
    _write(res, "sim.json", {"benchmark": "bench_sim.py", "command": "python benchmarks/bench_sim.py --runs 3",
                             "machine": dict(MACHINE, cores=4, load=3.5), "figures": {"sim.frames_per_s": 41.26,
                                                                            "sim.new_thing": 0.5}})
    text = wt.render(res)
    table = text[text.index("| figure |"):]
    peers_cmd, peers_machine = "`python benchmarks/bench_peers.py --cases kitti06`", "Test CPU 3000, 2 cores, 2026-01-02"
    sim_cmd, sim_machine = "`python benchmarks/bench_sim.py --runs 3`", "Test CPU 3000, 4 cores, load 3.5, 2026-01-02"
    assert table == "\n".join([
        "| figure | latest | target | met | command | machine |",
        "|---|---|---|---|---|---|",
        f"| KITTI 06 frames 0-50: ATE, ours / ORB-SLAM3 (same run) | 0.85x | ≤ 0.90x | yes | {peers_cmd} | {peers_machine} |",
        f"| KITTI 06 frames 0-50: CPU per frame, ours / ORB-SLAM3 (same run) | 1.23x | ≤ 1.00x | **no** | {peers_cmd} | {peers_machine} |",
        f"| KITTI 06 frames 0-50: ATE RMSE, ours | 34.10 mm |  |  | {peers_cmd} | {peers_machine} |",
        f"| simulator: stereo frames per second, 640x480 | 41.3/s | ≥ 30.0/s | yes | {sim_cmd} | {sim_machine} |",
        f"| `sim.new_thing` | 0.5000 |  |  | {sim_cmd} | {sim_machine} |",
    ]) + "\n"
    assert text.startswith("# Benchmarks\n")


def test_bad_results_are_named(wt, tmp_path):
    res = tmp_path / "results"
    _write(res, "a.json", {"benchmark": "x", "command": "c", "machine": MACHINE, "figures": {"f": "fast"}})
    with pytest.raises(wt.ResultsError, match=r"a.json: figure 'f' is 'fast', not a number"):
        wt.render(res)
    _write(res, "a.json", {"benchmark": "x", "figures": {}})
    with pytest.raises(wt.ResultsError, match=r"a.json: missing command, machine"):
        wt.render(res)
    (res / "a.json").write_text("{not json")
    assert wt.main(["--results", str(res), "--out", str(tmp_path / "b.md")]) == 2
    assert not (tmp_path / "b.md").exists()


def test_check_mode_and_the_committed_page(wt, tmp_path):
    res = tmp_path / "results"
    _write(res, "sim.json", {"benchmark": "bench_sim.py", "command": "c", "machine": MACHINE,
                             "figures": {"sim.frames_per_s": 12.0}})
    out = tmp_path / "bench.md"
    assert wt.main(["--results", str(res), "--out", str(out), "--check"]) == 1   # not written yet
    assert wt.main(["--results", str(res), "--out", str(out)]) == 0
    assert "| 12.0/s | ≥ 30.0/s | **no** |" in out.read_text()
    assert wt.main(["--results", str(res), "--out", str(out), "--check"]) == 0
    # the page in docs/ is what the committed JSON gives (it cannot drift from the benchmarks' output)
    assert wt.main(["--check"]) == 0


def test_results_file_records_the_command_without_json_out():
    rf = _load("results_file")
    assert rf.command_line(["benchmarks/bench_sim.py", "--runs", "3", "--json-out", "x.json", "--frames", "20"]) == \
        "python benchmarks/bench_sim.py --runs 3 --frames 20"
    assert rf.command_line(["/a/b/benchmarks/bench_peers.py", "--json-out=x.json", "--cases", "kitti06,sim"]) == \
        "python benchmarks/bench_peers.py --cases kitti06,sim"
    m = rf.machine()
    assert {"cpu", "cores", "date"} <= set(m) <= {"cpu", "cores", "date", "load"} and m["cores"] >= 1
