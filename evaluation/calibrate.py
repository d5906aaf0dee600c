"""Fit the engine's confidence (``service.engine.confidence``) on parts it never saw, in groups.

    python -m evaluation.calibrate                        # writes models/confidence.json
    python -m evaluation.calibrate --quick --out /tmp/c.json   # a few objects, for a try

It is fitted on two sources of answers (docs/decisions.md#calibration-that-transfers):

- the project's own parts (the model's training objects, group ``trained``): the families a
  cell sends (full clouds: so3, noisy, sparse, partial; depth-camera views with and without
  their viewpoint; views of parts on a table; junk), and every so3 cloud and sensor view once
  more with its own part left out of the candidates (its right answer is then no match);
- the corpus (``evaluation.calibration_corpus``): pybullet_data's other meshes in groups,
  registered at run time (as meshes and as clouds) and seen under several sensor profiles,
  on tables and in bins, beside foreign parts and junk.

Each answer's measures and whether it was right (the right part, ADD-S < 0.1) are kept; a
logistic regression over the measures is fitted. How it transfers is measured by holding each
group out in turn: the calibration fitted (and its threshold chosen) on the other groups
scores the held-out group's answers; ECE, AUROC and, at that threshold, coverage (the share of
right answers accepted), precision and false accepts are reported per family and per group.
The shipped calibration is fitted on every group and checked once more on the evaluation's
unseen parts and its foreign parts, which neither fit sees. Answers refused before any search
(no part of that size) are left out: their confidence is 0 by construction.
"""

from __future__ import annotations

import argparse
import json
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from tqdm import tqdm

from evaluation.calibration_corpus import PER_GROUP, corpus_rows
from evaluation.calibration_corpus import row as corpus_row
from evaluation.cases import FOREIGN, Case, make_cases
from evaluation.evaluate_mapping import prepare_engine
from evaluation.metrics import auroc, expected_calibration_error
from service.engine.confidence import FEATURES, Calibration
from service.engine.engine import Engine
from service.engine.mapping import file_sha256
from service.engine.tuning import BIN_ACCEPT
from service.settings import MODELS_DIR
from training.objects import load_manifest, load_object_meshes

RIDGE = 1e-2  # L2 weight on the standardised features' weights
# the share of accepted answers that must be right on the fitted cases, at the default threshold:
# above the 99 % that parts never fitted on must reach (at 0.99 the held-out check fell to 97 %)
PRECISION = 0.995


def cases_of(meshes: dict, scales: dict[str, float], per_object: int, seed: int) -> list[Case]:
    """The families a cell sends, for every object in ``meshes``."""
    counts = {"so3": per_object, "noisy": 1, "partial": 1, "sensor": 2 * per_object, "table": 1}
    cases = []
    for family, count in counts.items():
        cases += make_cases(family, meshes, scales, 2048, seed, count)
    cases += make_cases("sparse", meshes, scales, 2048, seed, 1, keep_shares=(0.1, 0.5))
    return cases


def answer(engine: Engine, case: Case, viewpoint: bool, leave_out: bool) -> dict | None:
    """The measures of the engine's answer to one case and whether it was right
    (``calibration_corpus.row``, the case's part its own truth)."""
    reference = engine.get(case.object_name)
    truth = None if reference is None else reference.points
    found = corpus_row(engine, case, viewpoint, leave_out, truth)
    return None if found is None else found | {"family": case.family}


def collect(engine: Engine, cases: list[Case], desc: str) -> list[dict]:
    """Every case's answer: sensor-like ones with and without the viewpoint; so3 and sensor
    also with their own part left out."""
    rows = []
    for case in tqdm(cases, desc=desc, leave=False):
        runs = [(False, False)]
        if "viewpoint" in case.params:
            runs.append((True, False))
        if case.family in ("so3", "sensor"):
            runs.append(("viewpoint" in case.params, True))
        for viewpoint, leave_out in runs:
            row = answer(engine, case, viewpoint, leave_out)
            if row is not None:
                rows.append(row | {"object": case.object_name, "left_out": leave_out})
    return rows


def fit_calibration(rows: list[dict], features: tuple[str, ...] = FEATURES) -> Calibration:
    """Logistic regression of rightness on the standardised measures, with a little ridge."""
    x = np.array([[row[name] for name in features] for row in rows])
    y = np.array([row["right"] for row in rows], dtype=np.float64)
    mean, spread = x.mean(axis=0), np.maximum(x.std(axis=0), 1e-9)
    z = (x - mean) / spread

    def loss(parameters: np.ndarray) -> tuple[float, np.ndarray]:
        weights, bias = parameters[:-1], parameters[-1]
        logits = z @ weights + bias
        p = 1 / (1 + np.exp(-logits))
        value = np.mean(np.logaddexp(0, logits) - y * logits) + RIDGE * weights @ weights
        gradient = np.append(z.T @ (p - y) / len(y) + 2 * RIDGE * weights, np.mean(p - y))
        return value, gradient

    # more fit, coverage or margin never lowers the confidence; a closer other pose never
    # raises it: the signs are constrained, so the answer's meaning cannot invert
    signs = {"fit": 1, "coverage": 1, "margin": 1, "alike": -1, "misfit": -1, "missed": -1,
             "chain": 1, "seen": 1, "through": -1, "explained": 1, "unexplained": -1,
             "around": -1}  # fmt: skip
    bounds = [
        (0, None) if signs.get(n) == 1 else (None, 0) if signs.get(n) == -1 else (None, None)
        for n in features
    ] + [(None, None)]
    start = np.zeros(len(features) + 1)
    solved = minimize(loss, start, jac=True, method="L-BFGS-B", bounds=bounds)
    return Calibration(features, solved.x[:-1], float(solved.x[-1]), mean, spread, {})


def matched(rows: list[dict], scores: np.ndarray, thresholds) -> np.ndarray:
    """Which answers the service makes a "match" at these ``thresholds`` (one, or one a
    row): an answer of a bin's reading from ``BIN_ACCEPT`` on, never one whose look-alikes fit
    alike (``Engine.judge``, ``look_alikes.doubt``)."""
    floor = np.array([BIN_ACCEPT if row.get("in_bin") else 0.0 for row in rows])
    doubted = np.array([bool(row.get("doubted")) for row in rows], dtype=bool)
    return (scores >= np.maximum(thresholds, floor)) & ~doubted


def judge(calibration: Calibration, rows: list[dict], accept: float) -> dict:
    """How well the calibration does on ``rows``."""
    scores = np.array([calibration.confidence(row) for row in rows])
    right = np.array([row["right"] for row in rows])
    accepted = matched(rows, scores, accept)
    return {
        "answers": len(rows),
        "right": float(right.mean()),
        "ece": expected_calibration_error(scores, right),
        "auroc": auroc(scores, right),
        "accepted": float(accepted.mean()),
        "precision_of_accepted": float(right[accepted].mean()) if accepted.any() else None,
        "wrong_accepted": float(accepted[~right].mean()) if (~right).any() else None,
        "right_accepted": float(accepted[right].mean()) if right.any() else None,
    }


def acceptance(calibration: Calibration, rows: list[dict]) -> float:
    """The lowest threshold at which at least ``PRECISION`` of the accepted answers of ``rows``
    are right: the service's default acceptance threshold."""
    scores = np.array([calibration.confidence(row) for row in rows])
    right = np.array([row["right"] for row in rows])
    for threshold in np.arange(0.5, 0.995, 0.01):
        accepted = matched(rows, scores, threshold)
        if accepted.any() and right[accepted].mean() >= PRECISION:
            return round(float(threshold), 2)
    return 0.99


GROUP_FAMILIES = ("full", "view", "table", "bin", "left-out", "foreign", "junk")
# answers of a registered part (its precision is the target's) and of one that is not (every
# "match" there is a false accept): docs/decisions.md#registered-or-not
REGISTERED, NOT_REGISTERED = GROUP_FAMILIES[:4], GROUP_FAMILIES[4:]
FULL_KINDS = ("so3", "noisy", "sparse", "partial", "full", "paper-poses")


def family_of(row: dict) -> str:
    """The family a row's answer is reported in (``GROUP_FAMILIES``)."""
    if row.get("left_out") or row["family"] == "left-out":
        return "left-out"
    if row["family"] in FULL_KINDS:
        return "full"
    if row["family"] == "sensor":
        return "view"
    return row["family"]


def held_out(rows: list[dict], features: tuple[str, ...] = FEATURES) -> list[float]:
    """Each row's confidence from the calibration fitted, and its threshold chosen, on every
    other group; and that threshold: (scores, thresholds), in the rows' order."""
    groups = sorted({row["group"] for row in rows})
    scores, thresholds = np.zeros(len(rows)), np.zeros(len(rows))
    for group in groups:
        inside = [row for row in rows if row["group"] != group]
        calibration = fit_calibration(inside, features)
        threshold = acceptance(calibration, inside)
        for index, row in enumerate(rows):
            if row["group"] == group:
                scores[index], thresholds[index] = calibration.confidence(row), threshold
    return scores, thresholds


def transfer_report(rows: list[dict], scores: np.ndarray, thresholds: np.ndarray) -> dict:
    """Per family and per group: how the held-out scores do at their fold's threshold."""

    def figures(chosen: np.ndarray) -> dict:
        right = np.array([rows[i]["right"] for i in np.flatnonzero(chosen)], dtype=bool)
        score = scores[chosen]
        accepted = matched([rows[i] for i in np.flatnonzero(chosen)], score, thresholds[chosen])
        return {
            "answers": int(chosen.sum()),
            "right": float(right.mean()) if len(right) else None,
            "ece": expected_calibration_error(score, right) if len(right) else None,
            "auroc": auroc(score, right),
            "coverage": float(accepted[right].mean()) if right.any() else None,
            "precision": float(right[accepted].mean()) if accepted.any() else None,
            "false_accepts": float(accepted[~right].mean()) if (~right).any() else None,
        }

    families = np.array([family_of(row) for row in rows])
    groups = np.array([row["group"] for row in rows])
    report = {
        "all": figures(np.ones(len(rows), dtype=bool)),
        "registered": figures(np.isin(families, REGISTERED)),
        "not_registered": figures(np.isin(families, NOT_REGISTERED)),
    }
    present = [family for family in GROUP_FAMILIES if (families == family).any()]
    report["families"] = {family: figures(families == family) for family in present}
    report["groups"] = {g: figures(groups == g) for g in sorted(set(groups))}
    return report


def print_report(report: dict) -> None:
    print(f"{'held out':14s} {'answers':>7s} {'right':>6s} {'ece':>6s} {'auroc':>6s} "
          f"{'cover':>6s} {'prec':>6s} {'false':>6s}")  # fmt: skip
    lines = [(name, report[name]) for name in ("all", "registered", "not_registered")]
    lines += list(report["families"].items())
    for name, figures in lines + list(report["groups"].items()):
        cells = [figures[k] for k in ("right", "ece", "auroc", "coverage", "precision",
                                      "false_accepts")]  # fmt: skip
        text = " ".join("     -" if c is None else f"{c:6.3f}" for c in cells)
        print(f"{name:14s} {figures['answers']:7d} {text}")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m evaluation.calibrate", description=__doc__)
    parser.add_argument("--out", type=Path, default=MODELS_DIR / "confidence.json")
    parser.add_argument("--quick", action="store_true", help="a few objects (a few minutes)")
    parser.add_argument("--per-object", type=int, default=2, help="so3 clouds per object")
    parser.add_argument("--per-group", type=int, default=PER_GROUP, help="corpus parts a group")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--rows", type=Path, default=None, help="also write every answer here")
    parser.add_argument(
        "--from-rows", type=Path, default=None, help="fit on a --rows file's answers instead"
    )
    args = parser.parse_args(argv)
    began = time.perf_counter()
    if args.from_rows:
        collected = json.loads(args.from_rows.read_text())
        model_hash = collected.get("model_sha256")
    else:
        collected, model_hash = collect_all(args)
    fit_rows, check_rows = collected["fit"], collected["check"]
    scores, thresholds = held_out(fit_rows)
    transfer = transfer_report(fit_rows, scores, thresholds)
    calibration = fit_calibration(fit_rows)
    accept = acceptance(calibration, fit_rows)
    about = {
        "fitted": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python -m evaluation.calibrate" + (" --quick" if args.quick else ""),
        "model_sha256": model_hash,
        "groups": sorted({row["group"] for row in fit_rows}),
        "fit": judge(calibration, fit_rows, accept),
        "held_out": transfer,
        "check": judge(calibration, check_rows, accept),
        "check_families": {
            family: judge(calibration, chosen, accept)
            for family in GROUP_FAMILIES
            if (chosen := [row for row in check_rows if family_of(row) == family])
        },
        "accept": accept,
        "seconds": round(time.perf_counter() - began, 1),
    }
    about["thresholds"] = {
        f"{t:.2f}": {
            "fit": judge(calibration, fit_rows, t),
            "check": judge(calibration, check_rows, t),
        }
        for t in (0.5, 0.7, 0.8, 0.9, 0.95)
    }
    calibration = Calibration(*[getattr(calibration, f) for f in ("features", "weights",
        "bias", "mean", "spread")], about, accept)  # fmt: skip
    if args.rows:
        args.rows.write_text(json.dumps(collected | {"model_sha256": model_hash}, default=float))
    calibration.save(args.out)
    manifest = args.out.parent / "manifest.json"
    if manifest.exists() and args.out.parent.resolve() == MODELS_DIR.resolve():
        record = json.loads(manifest.read_text())  # the release lists what it ships
        record["files"][args.out.name] = {
            "sha256": file_sha256(args.out),
            "bytes": args.out.stat().st_size,
        }
        record["confidence"] = {k: about[k] for k in ("fitted", "command", "fit", "check")}
        manifest.write_text(json.dumps(record, indent=2) + "\n")
    print_report(transfer)
    for part in ("fit", "check"):
        print(part, about[part])
    print(f"confidence calibration written to {args.out} in {about['seconds']:.0f} s")
    return about


def collect_all(args) -> tuple[dict, str]:
    """The answers to fit on (the project's own parts, group ``trained``, and the corpus's
    groups) and to check on (the evaluation's unseen parts and foreign parts)."""
    seen, unseen = load_manifest(split="seen"), load_manifest(split="unseen")
    registered = [s for s in unseen if s.name not in FOREIGN]
    foreign = [s for s in unseen if s.name in FOREIGN]
    engine, _ = prepare_engine(MODELS_DIR / "dpc_mn.onnx", MODELS_DIR / "gallery.npz", registered)
    step = 6 if args.quick else 1
    fit_meshes = load_object_meshes(seen[::step])
    check_meshes = load_object_meshes(registered[::step])
    foreign_meshes = load_object_meshes(foreign[:: max(1, step // 2)])
    scales = {name: engine.get(name).scale for name in engine.names()}
    scales |= {
        name: float(np.linalg.norm(m.vertices - m.vertices.mean(0), axis=1).max())
        for name, m in foreign_meshes.items()
    }
    junk = make_cases("junk", {}, {n: scales[n] for n in engine.names()}, 2048, args.seed, 2)
    fit_rows = collect(engine, cases_of(fit_meshes, scales, args.per_object, args.seed), "fit")
    fit_rows += collect(engine, junk, "junk")
    fit_rows = [row | {"group": "trained"} for row in fit_rows]
    check_cases = cases_of(check_meshes, scales, args.per_object, args.seed + 1)
    check_cases += make_cases("foreign", foreign_meshes, scales, 2048, args.seed + 1, 2)
    check_rows = collect(engine, check_cases, "check")
    for name in [spec.name for spec in registered]:
        engine.remove(name)  # the corpus's groups beside the shipped gallery alone
    per_group = 2 if args.quick else args.per_group
    groups = None if not args.quick else ("random-0xx", "laikago")
    fit_rows += corpus_rows(engine, per_group, args.seed, groups)
    return {"fit": fit_rows, "check": check_rows}, engine.mapper.model_hash


if __name__ == "__main__":
    main()
