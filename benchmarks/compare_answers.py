"""Two runs' answers compared case by case: what a change moved.

    python -m benchmarks.engine_settings --records before.json
    (change the code)
    python -m benchmarks.engine_settings --records after.json
    python -m benchmarks.compare_answers before.json after.json

Cases are matched by their family, object and index; an answer moved when its label,
verdict or outcome differs, or its confidence, rotation error or ADD-S by more than
``--tolerance``. Exit status 0 when nothing moved.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

COMPARED = ("label", "verdict", "outcome_ok", "success")
MEASURED = ("confidence", "rot_err_deg", "add_s")


def key(record: dict) -> tuple:
    return (record["study"], record["system"], record["family"], record["object"], record["case"])


def moved(before: dict, after: dict, tolerance: float) -> list[str]:
    """What differs between two answers to one case."""
    said = [
        f"{k} {before.get(k)} -> {after.get(k)}" for k in COMPARED if before.get(k) != after.get(k)
    ]
    for k in MEASURED:
        a, b = before.get(k), after.get(k)
        if (a is None) != (b is None) or (a is not None and abs(a - b) > tolerance):
            said.append(f"{k} {a} -> {b}")
    return said


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.compare_answers")
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--tolerance", type=float, default=1e-6)
    args = parser.parse_args(argv)
    before = {key(r): r for r in json.loads(args.before.read_text())}
    after = {key(r): r for r in json.loads(args.after.read_text())}
    missing = sorted(set(before) ^ set(after))
    changes = {k: moved(before[k], after[k], args.tolerance) for k in before.keys() & after.keys()}
    changes = {k: v for k, v in changes.items() if v}
    for k, said in sorted(changes.items()):
        print(" / ".join(map(str, k[2:])), ": ", "; ".join(said))
    print(
        f"{len(before.keys() & after.keys())} cases compared, {len(changes)} moved, "
        f"{len(missing)} in one run only"
    )
    return 0 if not changes and not missing else 1


if __name__ == "__main__":
    sys.exit(main())
