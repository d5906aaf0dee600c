"""The report on single views and on knowing when not to answer (issues 11 and 16).

From the records of ``evaluation.evaluate``: whether the engine's answers can be acted on
(coverage, false accepts, precision of accepted answers, right outcomes) per family and
object set, with and without the viewpoint; calibration (ECE, AUROC, a reliability diagram);
the spread of the answered poses of a symmetric part; the time of each step on sensor
clouds; and the issues' targets, met or missed. ``evaluation.report`` writes them into the
README, results.json and the plots.
"""

from __future__ import annotations

import math
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from evaluation.latency import latency_stats  # noqa: E402
from evaluation.metrics import (  # noqa: E402
    auroc,
    expected_calibration_error,
    reliability_bins,
    summarize,
    symmetric_spread,
)

STUDY = "full-gallery"
SYSTEMS = ("engine", "engine-no-viewpoint")
VERDICT_FAMILIES = (  # the rows of the verdict table, in order
    "paper-poses",
    "so3",
    "noisy",
    "partial",
    "sensor",
    "table",
    "units",
    "symmetric",
    "foreign",
    "junk",
)
VERDICT_SETS = ("seen", "unseen", "junk")
CALIBRATION_SETS = {  # name -> the object sets it pools
    "seen": ("seen",),
    "never trained on (unseen, junk)": ("unseen", "junk"),
    "all": ("seen", "unseen", "junk"),
}
SYMMETRIC_TARGET_DEG = 2.0


def _select(records: list[dict], **where) -> list[dict]:
    return [r for r in records if all(r.get(k) == v for k, v in where.items())]


def _percent(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{100 * value:.1f} %"


def _number(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{value:.{digits}f}"


# --- figures ---------------------------------------------------------------------------------


def verdict_rows(records: list[dict]) -> list[dict]:
    """summarize() (with its verdict figures) per system, family, view and object set."""
    rows = []
    for system in SYSTEMS:
        for family in VERDICT_FAMILIES:
            chosen = _select(records, study=STUDY, system=system, family=family)
            views = sorted({r.get("view") for r in chosen}, key=str)
            for view in views:
                for split in VERDICT_SETS:
                    subset = [r for r in chosen if r.get("view") == view and r["set"] == split]
                    if subset:
                        summary = summarize(subset)
                        rows.append(
                            {"system": system, "family": family, "view": view, "set": split}
                            | summary
                        )
    return rows


def symmetric_rows(records: list[dict]) -> list[dict]:
    """Per system and group of one symmetric surface: the spread of the answered rotations."""
    rows = []
    for system in SYSTEMS:
        chosen = _select(records, study=STUDY, system=system, family="symmetric")
        for group in dict.fromkeys(r["group"] for r in chosen):
            members = [r for r in chosen if r["group"] == group]
            rotations = [r.get("rotation") for r in members]
            rows.append(
                {
                    "system": system,
                    "group": group,
                    "set": members[0]["set"],
                    "members": len(members),
                    "label_ok": float(np.mean([r["label_ok"] for r in members])),
                    "accepted": float(np.mean([r["accepted"] for r in members])),
                    "spread_deg": symmetric_spread(rotations),
                    # what a robot acts on: the answers it is told to trust
                    "spread_match_deg": symmetric_spread(
                        r.get("rotation") for r in members if r["accepted"]
                    ),
                }
            )
    return rows


def step_latency(records: list[dict], family: str = "sensor") -> list[dict]:
    """The engine's time per step (its ``timings_ms``) on one family's clouds, with the
    viewpoint: median and 95th percentile per step, in the order the steps ran."""
    chosen = _select(records, study=STUDY, system="engine", family=family)
    per_step: dict[str, list[float]] = defaultdict(list)
    for record in chosen:
        for step, ms in (record.get("timings_ms") or {}).items():
            per_step[step].append(float(ms))
    rows = []
    for step, values in per_step.items():
        stats = latency_stats(values, ("count", "median_ms", "p95_ms"))
        rows.append(
            {
                "step": step,
                "cases": stats["count"],
                "median": stats["median_ms"],
                "p95": stats["p95_ms"],
            }
        )
    return rows


def calibration(records: list[dict]) -> dict:
    """ECE, AUROC and the reliability bins of the engine's confidence against success, per
    pool of object sets."""
    engine = _select(records, study=STUDY, system="engine")
    result = {}
    for name, sets in CALIBRATION_SETS.items():
        chosen = [r for r in engine if r["set"] in sets]
        confidence = [r.get("confidence") for r in chosen]
        right = [r["success"] for r in chosen]
        result[name] = {
            "cases": len(chosen),
            "with_confidence": sum(c is not None for c in confidence),
            "ece": expected_calibration_error(confidence, right),
            "auroc": auroc(confidence, right),
            "bins": reliability_bins(confidence, right),
        }
    return result


def plot_reliability(data: dict, path) -> None:
    """The reliability diagram: share right against mean confidence per bin, one line per
    pool, the diagonal for perfect calibration; bar widths are not drawn, counts are labels."""
    figure, axis = plt.subplots(figsize=(5.6, 5.0))
    axis.plot([0, 1], [0, 1], color="0.6", linestyle="--", label="calibrated")
    drawn = False
    for index, (name, pool) in enumerate(data.items()):
        bins = pool["bins"]
        if not bins:
            continue
        drawn = True
        x = [b["confidence"] for b in bins]
        y = [b["right"] for b in bins]
        label = f"{name}: ECE {_number(pool['ece'])}, AUROC {_number(pool['auroc'])}"
        axis.plot(x, y, marker="o", color=f"C{index}", label=label)
        for b in bins:
            axis.annotate(str(b["count"]), (b["confidence"], b["right"]), fontsize=6)
    if not drawn:
        axis.text(0.5, 0.5, "no answer gave a confidence", ha="center", va="center")
    axis.set(xlim=(0, 1), ylim=(0, 1.02), xlabel="confidence (mean per bin)")
    axis.set(ylabel="share right (label and ADD-S < 0.1)")
    axis.set_title("Reliability of the engine's confidence (full gallery)")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7, loc="upper left")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


# --- the issues' targets ---------------------------------------------------------------------


def _summary(records: list[dict], **where) -> dict:
    return summarize(_select(records, study=STUDY, **where))


def _per_set(records: list[dict], key: str, **where) -> dict[str, float]:
    return {
        split: _summary(records, set=split, **where).get(key, float("nan"))
        for split in ("seen", "unseen")
    }


def _both(figures: dict[str, float], met) -> tuple[str, bool]:
    text = " / ".join(f"{split} {_percent(v)}" for split, v in figures.items())
    values = [v for v in figures.values() if not math.isnan(v)]
    return text, bool(values) and all(met(v) for v in values)


def answer_targets(records: list[dict], symmetric: list[dict]) -> list[dict]:
    """The targets of issue 11 (single views), 12 (precise poses) and 16 (answers a cell can
    act on), on the full gallery with refinement; each met or missed, with its figure (seen /
    unseen)."""
    rows = []

    def add(issue: int, target: str, figure: str, met: bool) -> None:
        rows.append({"issue": issue, "target": target, "figure": figure, "met": bool(met)})

    sensor = {"system": "engine", "family": "sensor"}
    for key, goal, name in (("accuracy", 0.95, "recognition"), ("success", 0.90, "success")):
        add(11, f"sensor, with viewpoint: {name} ≥ {goal:.0%}", *_both(
            _per_set(records, key, **sensor), lambda v, g=goal: v >= g))  # fmt: skip
    add(11, "sensor, with viewpoint: precise ≥ 60%", *_both(
        _per_set(records, "precise", **sensor), lambda v: v >= 0.60))  # fmt: skip
    add(11, "sensor, without viewpoint: success ≥ 85%", *_both(
        _per_set(records, "success", system="engine-no-viewpoint", family="sensor"),
        lambda v: v >= 0.85))  # fmt: skip
    add(11, "partial: success ≥ 90%", *_both(
        _per_set(records, "success", system="engine", family="partial"),
        lambda v: v >= 0.90))  # fmt: skip
    latency = _summary(records, **sensor).get("latency_ms_median", float("nan"))
    add(11, "sensor: median in-process latency ≤ 50 ms", f"{_number(latency, 0)} ms",
        latency <= 50)  # fmt: skip
    for family in ("paper-poses", "so3", "noisy"):
        for key, name in (("accuracy", "recognition"), ("success", "success")):
            add(11, f"{family}: {name} ≥ 99% (full clouds no worse)", *_both(
                _per_set(records, key, system="engine", family=family),
                lambda v: v >= 0.99))  # fmt: skip

    full = ("so3", "noisy", "paper-poses")
    for family in full:
        add(12, f"{family}: precise ≥ 95%", *_both(
            _per_set(records, "precise", system="engine", family=family),
            lambda v: v >= 0.95))  # fmt: skip
        medians = _per_set(records, "median_add_s", system="engine", family=family)
        add(12, f"{family}: median ADD-S ≤ 0.005", " / ".join(
            f"{split} {_number(v, 4)}" for split, v in medians.items()),
            all(not math.isnan(v) and v <= 0.005 for v in medians.values()))  # fmt: skip
    turned = [r for r in _select(records, study=STUDY, system="engine") if r["family"] in full]
    self_similar = symmetric_parts(turned)
    within = {
        split: _share([
            r["rot_err_deg"] < ROTATION_TARGET_DEG for r in turned
            if r["set"] == split and r["label_ok"] and r["object"] not in self_similar
        ]) for split in ("seen", "unseen")
    }  # fmt: skip
    text, met = _both(within, lambda v: v >= 0.95)
    left_out = f"; {len(self_similar)} parts left out as symmetric ({SYMMETRIC_RULE}): "
    add(12, f"{'/'.join(full)}: rotation error < {ROTATION_TARGET_DEG:g}° for ≥ 95% of the"
        " answers on parts without a symmetry", text + left_out + ", ".join(sorted(self_similar)),
        met)  # fmt: skip

    def false_accepts(**where) -> float:
        return _summary(records, system="engine", **where).get("false_accepts", float("nan"))

    for name, where, goal in (
        ("junk", {"family": "junk"}, 0.0),
        ("millimetre clouds (units)", {"family": "units", "set": "unseen"}, 0.0),
        ("foreign full clouds", {"family": "foreign", "view": "full"}, 0.02),
        ("foreign sensor views", {"family": "foreign", "view": "sensor"}, 0.05),
    ):
        value = false_accepts(**where)
        add(16, f"false accepts on {name} ≤ {goal:.0%}", _percent(value), value <= goal)
    never_trained = [
        r for r in _select(records, study=STUDY, system="engine") if r["set"] != "seen"
    ]
    precision = summarize(never_trained).get("precision_accepted", float("nan"))
    add(16, "precision of all \"match\" answers ≥ 99% (unseen, foreign, junk)",
        _percent(precision), precision >= 0.99)  # fmt: skip
    for family in ("paper-poses", "so3", "noisy"):
        value = _summary(records, system="engine", family=family, set="unseen").get(
            "outcome_ok", float("nan")
        )
        add(16, f"{family}, unseen: ≥ 99% answered \"match\" and right", _percent(value),
            value >= 0.99)  # fmt: skip
    ece = expected_calibration_error(
        [r.get("confidence") for r in never_trained], [r["success"] for r in never_trained]
    )
    add(16, "calibration error (ECE) ≤ 0.05 (unseen, foreign, junk)", _number(ece), ece <= 0.05)
    table = _per_set(records, "success", system="engine", family="table")
    clean = _per_set(records, "success", **sensor)
    gaps = {split: table[split] - clean[split] for split in table}
    add(16, "table: success within 5 points of the clean sensor views",
        " / ".join(f"{s} {_percent(table[s])} vs {_percent(clean[s])}" for s in table),
        all(not math.isnan(g) and g >= -0.05 for g in gaps.values()))  # fmt: skip
    engine = [r for r in symmetric if r["system"] == "engine"]
    spreads = [r["spread_deg"] for r in engine if not math.isnan(r["spread_deg"])]
    worst = max(spreads) if spreads else float("nan")
    within = sum(s <= SYMMETRIC_TARGET_DEG for s in spreads)
    matches = [r.get("spread_match_deg", float("nan")) for r in engine]
    matches = [s for s in matches if not math.isnan(s)]
    figure = (
        f"{within} of {len(spreads)} groups within; largest spread {_number(worst, 1)}°"
        + (f" ({sum(s <= SYMMETRIC_TARGET_DEG for s in matches)} of {len(matches)} groups"
           " within among \"match\" answers)" if matches else "")
    )  # fmt: skip
    add(16, f"symmetric: answered rotations within {SYMMETRIC_TARGET_DEG:g}° of each other",
        figure, worst <= SYMMETRIC_TARGET_DEG)  # fmt: skip
    return rows


ROTATION_TARGET_DEG = 2.0
SYMMETRIC_TURN_DEG, SYMMETRIC_ADD_S = 5.0, 0.01
SYMMETRIC_RULE = (
    f"a part whose answer was turned more than {SYMMETRIC_TURN_DEG:g}° from the truth with an"
    f" ADD-S under {SYMMETRIC_ADD_S} maps onto itself: it has a symmetry"
)


def symmetric_parts(records: list[dict]) -> set[str]:
    """The parts some answer showed to be symmetric (``SYMMETRIC_RULE``): turned well away from
    the truth, yet its surface on the truth's within 1 % of the diameter."""
    return {
        r["object"]
        for r in records
        if r["label_ok"]
        and r.get("rot_err_deg") is not None
        and r["rot_err_deg"] > SYMMETRIC_TURN_DEG
        and r["add_s"] < SYMMETRIC_ADD_S
    }


def _share(flags: list[bool]) -> float:
    return float(np.mean(flags)) if flags else float("nan")


# --- the README ------------------------------------------------------------------------------


def readme_lines(answers: dict) -> list[str]:
    """The README's sections on single views and on knowing when not to answer."""
    lines = [
        "## Targets of issues 11 (single views), 12 (precise poses) and 16 (answers to act on)",
        "",
    ]
    lines += ["| issue | target | figure | |", "| --- | --- | --- | --- |"]
    for row in answers["targets"]:
        met = "met" if row["met"] else "MISSED"
        lines.append(f"| {row['issue']} | {row['target']} | {row['figure']} | {met} |")
    lines += [
        "",
        "## Knowing when not to answer (full gallery)",
        "",
        'Coverage: share answered `"match"`; false accepts: share answered `"match"` and'
        ' wrong (on foreign and junk every `"match"`); precision: share of the `"match"`'
        " answers that are right (label and ADD-S < 0.1); right outcome: accepted and right,"
        " or refused where no registered part is (for millimetre clouds also a refusal whose"
        " reasons name the units). `engine-no-viewpoint` is the same engine never told the"
        " viewpoint.",
        "",
        "| system | family | view | set | cases | coverage | false accepts | precision "
        "| right outcome | success | ECE | AUROC | confidence given |",
        "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in answers["verdicts"]:
        lines.append(
            f"| {r['system']} | {r['family']} | {r['view'] or 'full'} | {r['set']} | {r['cases']} "
            f"| {_percent(r['coverage'])} | {_percent(r['false_accepts'])} "
            f"| {_percent(r['precision_accepted'])} | {_percent(r['outcome_ok'])} "
            f"| {_percent(r['success'])} | {_number(r['ece'])} | {_number(r['auroc'])} "
            f"| {_percent(r['confidence_given'])} |"
        )
    lines += ["", "### Calibration of the confidence (engine, every family)", ""]
    lines += [
        "| pool | cases | with a confidence | ECE | AUROC |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for name, pool in answers["calibration"].items():
        lines.append(
            f"| {name} | {pool['cases']} | {pool['with_confidence']} | {_number(pool['ece'])} "
            f"| {_number(pool['auroc'])} |"
        )
    lines += ["", "### Symmetric parts: the spread of the answered rotations", ""]
    lines += [
        "Each group is one pose of the part turned about its symmetry axis by several angles"
        " (the same surface); the spread is the largest angle between two answered rotations,"
        ' of all answers and of the `"match"` ones (what a robot acts on; n/a under two).',
        "",
        "| system | group | set | members | label right | accepted | spread (°) "
        "| spread of matches (°) |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in answers["symmetric"]:
        lines.append(
            f"| {r['system']} | {r['group']} | {r['set']} | {r['members']} "
            f"| {_percent(r['label_ok'])} | {_percent(r['accepted'])} "
            f"| {_number(r['spread_deg'], 1)} | {_number(r.get('spread_match_deg'), 1)} |"
        )
    if answers["step_latency"]:
        lines += ["", "### Time per step on sensor clouds (engine, with viewpoint, in-process)", ""]
        lines += ["| step | cases | median (ms) | p95 (ms) |", "| --- | ---: | ---: | ---: |"]
        for r in answers["step_latency"]:
            lines.append(f"| {r['step']} | {r['cases']} | {r['median']:.1f} | {r['p95']:.1f} |")
    lines.append("")
    return lines


def answers_report(records: list[dict]) -> dict:
    """Every figure of this part of the report (written to results.json as ``answers``), from
    the records that say whether they were accepted (a run from before verdicts has none)."""
    records = [r for r in records if "accepted" in r]
    symmetric = symmetric_rows(records)
    return {
        "verdicts": verdict_rows(records),
        "calibration": calibration(records),
        "symmetric": symmetric,
        "step_latency": step_latency(records),
        "targets": answer_targets(records, symmetric),
    }
