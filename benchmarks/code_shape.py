"""The code's shape, read with ``ast`` from ``device/`` and ``host/``: the figures issue 38 sets targets for.

    .venv/bin/python benchmarks/code_shape.py [--list]

Prints the longest modules, configuration classes by field count, functions by parameter count
(``self``/``cls`` not counted), the number of ``: Any`` / ``-> Any`` annotations, and the places where
one object's attributes are set by name (``setattr`` on another object).  ``tests/test_layout.py`` asserts
the targets with the same functions.
"""

from __future__ import annotations

import argparse
import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = ("device", "host")
CONFIG_WORDS = ("Config", "Preset", "Settings")
ANY_SPELLINGS = {"Any", "typing.Any", "Any | None", "None | Any", "Optional[Any]"}


@dataclass(frozen=True)
class Shape:
    module_lines: list[tuple[str, int]]          # (path, lines), longest first
    config_fields: list[tuple[str, int]]         # (path:Class, fields), most first
    function_params: list[tuple[str, int]]       # (path:function, parameters), most first
    any_annotations: list[str]                   # path:line of each
    setattr_by_name: list[str]                   # path:line of each setattr on another object


def _sources(root: Path) -> list[Path]:
    return sorted(p for folder in FOLDERS for p in (root / folder).rglob("*.py"))


def _is_any(node: ast.expr | None) -> bool:
    return node is not None and ast.unparse(node).strip() in ANY_SPELLINGS


def measure(root: Path = ROOT) -> Shape:
    lines, configs, params, anys, setattrs = [], [], [], [], []
    for path in _sources(root):
        rel = str(path.relative_to(root))
        text = path.read_text()
        lines.append((rel, text.count("\n")))
        tree = ast.parse(text, rel)
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and any(w in node.name for w in CONFIG_WORDS):
                n = sum(isinstance(s, ast.AnnAssign) for s in node.body)
                configs.append((f"{rel}:{node.name}", n))
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                positional = a.posonlyargs + a.args
                n = len(positional) + len(a.kwonlyargs)
                if positional and positional[0].arg in ("self", "cls"):
                    n -= 1
                params.append((f"{rel}:{node.lineno}:{node.name}", n))
                every = positional + a.kwonlyargs + [x for x in (a.vararg, a.kwarg) if x is not None]
                anys += [f"{rel}:{x.lineno}" for x in every if _is_any(x.annotation)]
                if _is_any(node.returns):
                    anys.append(f"{rel}:{node.lineno}")
            elif isinstance(node, ast.AnnAssign) and _is_any(node.annotation):
                anys.append(f"{rel}:{node.lineno}")
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "setattr"
                  and node.args and not (isinstance(node.args[0], ast.Name) and node.args[0].id == "self")):
                setattrs.append(f"{rel}:{node.lineno}")
    return Shape(sorted(lines, key=lambda x: -x[1]), sorted(configs, key=lambda x: -x[1]),
                 sorted(params, key=lambda x: -x[1]), anys, setattrs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="list every offender, not only the counts")
    args = ap.parse_args()
    s = measure()
    over = {
        "modules over 600 lines": [f"{p} ({n})" for p, n in s.module_lines if n > 600],
        "config classes over 12 fields": [f"{p} ({n})" for p, n in s.config_fields if n > 12],
        "functions over 8 parameters": [f"{p} ({n})" for p, n in s.function_params if n > 8],
        "': Any' / '-> Any' annotations": s.any_annotations,
        "setattr on another object": s.setattr_by_name,
    }
    print(f"longest module: {s.module_lines[0][0]} ({s.module_lines[0][1]} lines)")
    print(f"largest config class: {s.config_fields[0][0]} ({s.config_fields[0][1]} fields)")
    print(f"most parameters: {s.function_params[0][0]} ({s.function_params[0][1]})")
    for what, items in over.items():
        print(f"{what}: {len(items)}")
        if args.list:
            for item in items:
                print(f"    {item}")


if __name__ == "__main__":
    main()
