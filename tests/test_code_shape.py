"""The code's shape (benchmarks/code_shape.py): short modules, small config classes, short parameter lists,
few ``Any`` annotations, and no object whose attributes another class sets by name."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _code_shape():
    spec = importlib.util.spec_from_file_location("code_shape", ROOT / "benchmarks" / "code_shape.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their annotations through sys.modules
    spec.loader.exec_module(module)
    return module


def test_the_tree_keeps_its_shape():
    s = _code_shape().measure(ROOT)
    assert [(p, n) for p, n in s.module_lines if n > 600] == []
    assert [(p, n) for p, n in s.config_fields if n > 12] == []
    assert [(p, n) for p, n in s.function_params if n > 8] == []
    assert len(s.any_annotations) < 80, s.any_annotations
    assert s.setattr_by_name == []


def test_each_measure_sees_a_bad_tree(tmp_path):
    bad = tmp_path / "device" / "bad.py"
    bad.parent.mkdir(parents=True)
    (tmp_path / "host").mkdir()
    fields = "\n".join(f"    f{i}: int = {i}" for i in range(13))
    bad.write_text("from typing import Any\n"
                   f"class WideConfig:\n{fields}\n"
                   "def many(a, b, c, d, e, f, g, h, i):\n    pass\n"
                   "def loose(x: Any) -> Any:\n    return x\n"
                   "def poke(other):\n    setattr(other, 'pose', None)\n"
                   + "\n" * 600)
    s = _code_shape().measure(tmp_path)
    assert s.module_lines[0] == ("device/bad.py", bad.read_text().count("\n"))
    assert s.config_fields == [("device/bad.py:WideConfig", 13)]
    assert s.function_params[0] == ("device/bad.py:16:many", 9)
    assert s.any_annotations == ["device/bad.py:18", "device/bad.py:18"]
    assert s.setattr_by_name == ["device/bad.py:21"]
