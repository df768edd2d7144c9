"""Issue 39: the short version of ``benchmarks/bench_fuzz.py``: a few hundred mutated input files (poses,
rigs, calibrations, device.toml, session files, PNG images, the host store's files) through the commands
that read them, in this process: no input may end in a traceback."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
INPUTS = 200


def _bench():
    spec = importlib.util.spec_from_file_location("bench_fuzz", ROOT / "benchmarks" / "bench_fuzz.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bench():
    return _bench()


def test_mutators_are_seeded_and_change_the_input(bench):
    import random

    data = b"0.0 1.5 -2 3e-3 0 0 0 1\n0.1 1.6 -2 3e-3 0 0 0 1\n"
    for name, mutate in bench.TEXT_MUTATORS.items():
        a = mutate(random.Random(3), data, "text")
        assert a == mutate(random.Random(3), data, "text"), name  # one seed, one input
        assert any(mutate(random.Random(s), data, "text") != data for s in range(5)), name
    assert b"1e308" in bench.m_huge(random.Random(0), b"x: 1\n", "yaml") or \
        any(h in bench.m_huge(random.Random(0), b"x: 1\n", "yaml") for h in bench.HUGE)
    assert len(bench.m_nesting(random.Random(0), b"x = 1\n", "toml")) > 100


def test_a_traceback_is_counted(bench, tmp_path):
    """The harness tells a traceback from an exit code: a command that raises a non-project error counts."""
    handler = bench._TracebackLog()
    outcome, detail, _ = bench.run_one(["eval", "--gt", str(tmp_path / "none.tum"), "--est", "x"], handler)
    assert outcome == "ok" and detail == "2"  # a missing file: one line, exit 2
    outcome, _, _ = bench.run_one(["--no-such-option"], handler)
    assert outcome == "ok"  # argparse's SystemExit is not a traceback
    import stereopath.host.commands.eval as ev

    real = ev.run
    ev.run = lambda args: 1 / 0
    try:
        outcome, detail, where = bench.run_one(["eval", "--gt", "a", "--est", "b"], handler)
    finally:
        ev.run = real
    assert outcome == "traceback" and detail.startswith("ZeroDivisionError")


@pytest.mark.slow
def test_fuzzed_inputs_give_no_traceback(bench, tmp_path):
    targets = bench.build_workspace(tmp_path / "w", session_frames=6)
    kinds = {t.name.split("_")[0] for t in targets}
    assert {"tum", "kitti", "rig", "device", "session", "features", "store"} <= kinds
    cheap = [t for t in targets if t.cheap]
    res = bench.fuzz(cheap, tmp_path / "w", seed=39, max_inputs=INPUTS)
    assert res.tried == INPUTS and len(res.per_target) == len(cheap)
    assert res.tracebacks == [] and res.hangs == [], [f.__dict__ for f in res.tracebacks + res.hangs]
    assert len(res.exit_codes) >= 2  # some inputs were refused, some read
