"""The report on whole frames (issue 35, ``POST /detect``): figures, targets, plots and the
README's section, from the records of ``evaluation.detect`` (kept in ``frames.json`` beside
the report's ``results.json``).
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

MATCH = "match"
VISIBLE_BANDS = ((0.5, 1.01), (0.3, 0.5), (0.0, 0.3))  # recall per band; 1.01 takes 1.0 in
CURVE_BINS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.01)
PLOTS = {
    "recall": "frames_recall_vs_visible_share.png",
    "latency": "frames_latency.png",
}
# Issue 35's targets: on unseen parts registered at run time, a gallery of 50 or more.
TARGET_RECALL_50 = 0.95
TARGET_RECALL_30 = 0.80
TARGET_PRECISION = 0.995
TARGET_EMPTY = 0.99
TARGET_VGA_MS = 300.0
TARGET_HD_MS = 500.0
TARGET_REFERENCES = 50
DEFAULT_BUDGET_MS = 30_000  # the service's default request budget (limits.request_timeout_s)
WRONG_KINDS = ("duplicate", "wrong pose", "wrong label", "not registered", "nothing")
PIXEL_BANDS = (0, 500, 1000, 2000, 5000, None)  # an instance's pixels in the frame


def _registered(records: list[dict]) -> list[dict]:
    return [i for r in records for i in r["instances"] if i.get("registered", True)]


def band_recall(instances: list[dict], low: float, high: float) -> dict:
    """Registered instances whose visible share is in [low, high), and how many were found."""
    chosen = [
        i for i in instances if i.get("registered", True) and low <= i["visible_share"] < high
    ]
    found = sum(bool(i["found"]) for i in chosen)
    share = found / len(chosen) if chosen else None
    return {"instances": len(chosen), "found": found, "recall": share}


def _band_name(low: float, high: float) -> str:
    return f"{100 * low:.0f}-{100 * min(high, 1.0):.0f} %"


def summarize_frames(records: list[dict]) -> dict:
    """The figures of a group of frame records (``evaluation.detect.frame_record``)."""
    instances = _registered(records)
    matches = [d for r in records for d in r["detections"] if d["verdict"] == MATCH]
    right = sum(d["outcome"] == "right" for d in matches)
    wrong = {kind: sum(d["outcome"] == kind for d in matches) for kind in WRONG_KINDS}
    without = [r for r in records if not any(i["registered"] for i in r["instances"])]
    falsely = [r for r in without if any(d["verdict"] == MATCH for d in r["detections"])]
    latencies = [r["latency_ms"] for r in records if r.get("latency_ms") is not None]
    found_add_s = [i["add_s"] for i in instances if i["found"]]
    visible = [i for i in instances if i["visible_share"] >= 0.3]
    over = [r for r in records if (r.get("server_ms") or 0) > DEFAULT_BUDGET_MS]
    return {
        "frames": len(records),
        "failed": sum(bool(r.get("error")) for r in records),
        "over_default_budget": len(over),
        "instances": len(instances),
        "bands": {_band_name(lo, hi): band_recall(instances, lo, hi) for lo, hi in VISIBLE_BANDS},
        "matches": len(matches),
        "right_matches": right,
        "wrong_matches": wrong,
        "precision": right / len(matches) if matches else None,
        "frames_without_registered": len(without),
        "frames_without_registered_with_match": len(falsely),
        "posed_any_verdict_30": (
            sum(i["found_as"] is not None for i in visible) / len(visible) if visible else None
        ),
        "median_add_s": float(np.median(found_add_s)) if found_add_s else None,
        "latency_ms_median": float(np.median(latencies)) if latencies else None,
        "latency_ms_p95": float(np.percentile(latencies, 95)) if latencies else None,
    }


def by_pixels(records: list[dict]) -> list[dict]:
    """Found and posed shares of the registered instances ≥ 50 % visible, by the pixels they
    show in the frame."""
    instances = [i for i in _registered(records) if i["visible_share"] >= 0.5]
    rows = []
    for low, high in zip(PIXEL_BANDS[:-1], PIXEL_BANDS[1:], strict=True):
        top = np.inf if high is None else high
        chosen = [i for i in instances if low <= i["pixels"] < top]
        if chosen:
            rows.append(
                {
                    "band": f"{low:,}-{high:,}" if high else f"{low:,} or more",
                    "instances": len(chosen),
                    "found": sum(bool(i["found"]) for i in chosen) / len(chosen),
                    "posed": sum(i["found_as"] is not None for i in chosen) / len(chosen),
                }
            )
    return rows


def summarize_baseline(records: list[dict]) -> dict:
    instances = [i for r in records for i in r["instances"]]
    found_add_s = [i["add_s"] for i in instances if i["found"]]
    latencies = [r["latency_ms"] for r in records]
    return {
        "frames": len(records),
        "instances": len(instances),
        "bands": {_band_name(lo, hi): band_recall(instances, lo, hi) for lo, hi in VISIBLE_BANDS},
        "median_add_s": float(np.median(found_add_s)) if found_add_s else None,
        "latency_ms_median": float(np.median(latencies)) if latencies else None,
        "latency_ms_p95": float(np.percentile(latencies, 95)) if latencies else None,
    }


def _group(record: dict) -> str:
    size = "" if record["size"] == "640x480" else f", {record['size']}"
    split = "" if record["set"] == "none" else f", {record['set']}"
    return f"{record['family']}{split}{size}"


def curve(instances: list[dict]) -> list[dict]:
    rows = []
    for low, high in zip(CURVE_BINS[:-1], CURVE_BINS[1:], strict=True):
        band = band_recall(instances, low, high)
        if band["instances"]:
            rows.append({"low": low, "high": min(high, 1.0), **band})
    return rows


def told_pairs(records: list[dict], told: list[dict]) -> dict:
    """Per family of the frames posted again told their parts: their figures, and those of
    the same frames as first posted."""
    pairs = {}
    for family in ("scene", "bin"):
        again = [r for r in told if r["family"] == family]
        if again:
            stems = {(r["stem"], r["set"]) for r in again}
            first = [r for r in records if (r["stem"], r["set"]) in stems]
            pairs[family] = {"told": summarize_frames(again), "untold": summarize_frames(first)}
    return pairs


def frames_report(frames: dict) -> dict:
    """Everything the README's section and the plots need."""
    records = frames["records"]
    groups: dict[str, list[dict]] = {}
    for r in records:
        groups.setdefault(_group(r), []).append(r)
    unseen = [r for r in records if r["set"] == "unseen"]
    no_part = [r for r in records if r["family"] in ("empty", "foreign")]
    baseline = frames.get("baseline", [])
    baseline_stems = {(b["stem"], b["set"]) for b in baseline}
    engine_on_baseline = [r for r in records if (r["stem"], r["set"]) in baseline_stems]
    return {
        "groups": {name: summarize_frames(chosen) for name, chosen in groups.items()},
        "unseen": summarize_frames(unseen),
        "seen": summarize_frames([r for r in records if r["set"] == "seen"]),
        "precision_pool": summarize_frames(unseen + no_part),
        "no_part": summarize_frames(no_part),
        "vga_scene": summarize_frames(
            [r for r in records if r["family"] == "scene" and r["size"] == "640x480"]
        ),
        "hd": summarize_frames([r for r in records if r["size"] != "640x480"]),
        "bodies": {
            body: summarize_frames([r for r in records if r["body"] == body])
            for body in sorted({r["body"] for r in records})
        },
        "baseline": summarize_baseline(baseline),
        "engine_on_baseline_frames": summarize_frames(engine_on_baseline),
        "engine_told_on_baseline_frames": summarize_frames(
            [r for r in frames.get("told", []) if (r["stem"], r["set"]) in baseline_stems]
        ),
        "told": told_pairs(records, frames.get("told", [])),
        "curves": {
            "engine, unseen": curve(_registered(unseen)),
            "engine, seen": curve(_registered([r for r in records if r["set"] == "seen"])),
            "engine, the baseline's frames": curve(_registered(engine_on_baseline)),
            "FPFH + RANSAC + ICP (told the parts), its frames": curve(
                [i for b in baseline for i in b["instances"]]
            ),
        },
        "targets": frame_targets(frames, unseen, no_part, records),
    }


def _percent(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{100 * value:.1f} %"


def _ms(value) -> str:
    return "n/a" if value is None else f"{value:,.0f}"


def frame_targets(frames: dict, unseen: list, no_part: list, records: list) -> list[dict]:
    rows = []

    def add(target: str, figure: str, met: bool) -> None:
        rows.append({"target": target, "figure": figure, "met": bool(met)})

    instances = _registered(unseen)
    for (low, high), goal in (((0.5, 1.01), TARGET_RECALL_50), ((0.3, 0.5), TARGET_RECALL_30)):
        band = band_recall(instances, low, high)
        add(
            f"unseen instances {_band_name(low, high)} visible: ≥ {100 * goal:.0f} % found",
            f"{_percent(band['recall'])} ({band['found']} of {band['instances']})",
            band["recall"] is not None and band["recall"] >= goal,
        )
    pool = summarize_frames(unseen + no_part)
    add(
        f'precision of "match" detections ≥ {100 * TARGET_PRECISION:.1f} % (unseen, empty,'
        " foreign frames)",
        f"{_percent(pool['precision'])} ({pool['right_matches']} of {pool['matches']})",
        pool["precision"] is not None and pool["precision"] >= TARGET_PRECISION,
    )
    empty = summarize_frames(no_part)
    clean = empty["frames"] - empty["frames_without_registered_with_match"]
    share = clean / empty["frames"] if empty["frames"] else None
    add(
        f'frames with no registered part: no "match" in ≥ {100 * TARGET_EMPTY:.0f} %',
        f"{_percent(share)} ({clean} of {empty['frames']})",
        share is not None and share >= TARGET_EMPTY,
    )
    for size, goal, label in (
        ("640x480", TARGET_VGA_MS, "640 × 480 scene frame (up to 6 parts)"),
        ("1280x720", TARGET_HD_MS, "1280 × 720 scene frame"),
    ):
        chosen = [r for r in records if r["family"] == "scene" and r["size"] == size]
        figures = summarize_frames(chosen)
        median = figures["latency_ms_median"]
        add(
            f"{label}: median ≤ {goal:.0f} ms through HTTP",
            f"{_ms(median)} ms (p95 {_ms(figures['latency_ms_p95'])}, {len(chosen)} frames)",
            median is not None and median <= goal,
        )
    add(
        f"gallery of at least {TARGET_REFERENCES} references",
        f"{frames['references']} references",
        frames["references"] >= TARGET_REFERENCES,
    )
    return rows


# --- plots -----------------------------------------------------------------------------------


def plot_recall(report: dict, path) -> None:
    figure, axis = plt.subplots(figsize=(6.4, 4.2))
    styles = ("C0-o", "C0--s", "C4:^", "C2-D")
    for (name, rows), style in zip(report["curves"].items(), styles, strict=True):
        if not rows:
            continue
        centres = [(r["low"] + r["high"]) / 2 for r in rows]
        axis.plot(centres, [r["recall"] for r in rows], style, label=name)
    axis.axvspan(0.0, 0.3, color="0.9", zorder=0)
    axis.set(xlabel="visible share of the instance", ylabel='found ("match", ADD-S < 0.1)')
    axis.set(xlim=(0, 1), ylim=(0, 1.05), title="Whole frames: recall against the visible share")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_latency(frames: dict, path) -> None:
    groups: dict[str, list[float]] = {}
    for r in frames["records"]:
        groups.setdefault(_group(r), []).append(r["latency_ms"])
    baseline = [b["latency_ms"] for b in frames.get("baseline", [])]
    if baseline:
        groups["FPFH + RANSAC + ICP (told the parts)"] = baseline
    names = list(groups)
    figure, axis = plt.subplots(figsize=(7.5, 0.45 * len(names) + 1.6))
    axis.boxplot([groups[n] for n in names], vert=False, whis=(5, 95), showfliers=True)
    axis.set_yticks(range(1, len(names) + 1), names, fontsize=7)
    axis.axvline(TARGET_VGA_MS, color="C3", linestyle="--", label="300 ms (640 × 480 target)")
    axis.axvline(TARGET_HD_MS, color="C1", linestyle=":", label="500 ms (1280 × 720 target)")
    axis.set(xscale="log", xlabel="time per frame through HTTP (ms, log scale)")
    axis.set_title("Whole frames: time per frame (box: quartiles, whiskers: 5-95 %)")
    axis.invert_yaxis()
    axis.grid(alpha=0.3, axis="x")
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def write_plots(frames: dict, report: dict, out) -> None:
    plot_recall(report, out / PLOTS["recall"])
    plot_latency(frames, out / PLOTS["latency"])


# --- the README ------------------------------------------------------------------------------


def _band_cells(bands: dict) -> str:
    cells = []
    for band in bands.values():
        cells.append(
            "" if not band["instances"] else f"{_percent(band['recall'])} ({band['instances']})"
        )
    return " | ".join(cells)


def readme_lines(frames: dict, report: dict) -> list[str]:
    plan = frames["plan"]
    registered = frames.get("registered", {})
    lines = [
        "## Whole frames (issue 35, `POST /detect`)",
        "",
        f"Written by `{frames.get('command', 'python -m evaluation.detect')}` (seed"
        f" {frames['seed']}, {frames['seconds'] / 60:.1f} min); frames of `evaluation.frames`:"
        " pybullet_data meshes rescaled to a table's sizes (radius 3-15 cm), dropped onto a"
        " table or into a bin by pybullet's physics, ray cast at 640 × 480 (f = 525 px) or"
        " 1280 × 720 (f = 1050 px) from 0.6-1.2 m, 40-80° above the table, with depth noise"
        " σ = 0.15 % of the distance, 1 mm steps and half the pixels at depth jumps dropped."
        f" Posted to a real `python -m service` holding {frames['references']} references: the"
        f" shipped gallery plus {len(registered)} registered at run time through"
        " `POST /references` as their rescaled meshes (the unseen objects, and seen ones the"
        " frames hold at another size than the shipped reference, replaced). Each frame as the"
        " driver writes it: the organized binary PCD, or (one frame in"
        f" {plan['depth_png_every']}) a 16-bit depth PNG with its intrinsics. Unseen"
        " frames hold unseen parts only (the four kept out of the gallery as unregistered"
        " ones); seen frames seen parts only. Seeds: the unseen and part-free frames"
        f" {frames['seed']}, the seen ones {frames['seed'] + 1000}, the 1280 × 720 ones"
        f" {frames['seed'] + 500}: not those `evaluation.calibrate_detect` fits and checks the"
        " detection's confidence on (11, 12 by default).",
        "",
        'An instance is found when a `"match"` of its label has ADD-S < 0.1 of it (each'
        ' instance found once, detections taken by confidence); a `"match"` that finds none'
        " is wrong: a duplicate (of an instance found already), a wrong pose, or by the pixels"
        " it claims a wrong label, an unregistered part, or nothing (the supports). The visible"
        " share is the pixels an instance shows over those it would show alone. Posed (any"
        " verdict): the share of instances ≥ 30 % visible that some detection, of any verdict,"
        " puts within ADD-S < 0.1: what a stricter verdict left unfound.",
        "",
        "### Targets (unseen parts registered at run time)",
        "",
        "| target | figure | |",
        "| --- | --- | --- |",
    ]
    for row in report["targets"]:
        lines.append(f"| {row['target']} | {row['figure']} | {'met' if row['met'] else 'MISSED'} |")
    lines += [
        "",
        f"![recall]({PLOTS['recall']})",
        "",
        f"![latency]({PLOTS['latency']})",
        "",
        "### Per family",
        "",
        "Recall cells: the share found (registered instances in the band).",
        "",
        "| frames | n | instances | found, ≥ 50 % visible | 30-50 % | < 30 % | posed (any"
        ' verdict) | "match" | precision | wrong: dup. / pose / label / unreg. / nothing'
        " | no-part frames with a match | median ADD-S | time median / p95 (ms) |",
        "| --- |" + " ---: |" * 8 + " --- |" + " ---: |" * 3,
    ]
    for name, s in report["groups"].items():
        wrong = " / ".join(str(s["wrong_matches"][k]) for k in WRONG_KINDS)
        no_part = (
            f"{s['frames_without_registered_with_match']} of {s['frames_without_registered']}"
            if s["frames_without_registered"]
            else ""
        )
        add_s = "n/a" if s["median_add_s"] is None else f"{s['median_add_s']:.4f}"
        lines.append(
            f"| {name} | {s['frames']} | {s['instances']} | {_band_cells(s['bands'])} "
            f"| {_percent(s['posed_any_verdict_30'])} | {s['matches']} | {_percent(s['precision'])}"
            f" | {wrong} | {no_part} | {add_s} "
            f"| {_ms(s['latency_ms_median'])} / {_ms(s['latency_ms_p95'])} |"
        )
    every = summarize_frames(frames["records"])
    lines += [
        "",
        f"Frames without an answer (an error: counted as nothing detected): {every['failed']} of"
        f" {every['frames']}; answered after more than the service's default budget of"
        f" {DEFAULT_BUDGET_MS / 1000:.0f} s (the evaluation's server allows"
        f" {frames.get('request_timeout_s', 300):.0f} s, so that they are measured, not"
        f" abandoned): {every['over_default_budget']}.",
    ]
    lines += ["", "By the pixels an instance shows (registered, ≥ 50 % visible, every frame):", ""]
    lines += ["| pixels | instances | found | posed (any verdict) |"]
    lines += ["| --- | ---: | ---: | ---: |"]
    for row in by_pixels(frames["records"]):
        lines.append(
            f"| {row['band']} | {row['instances']} | {_percent(row['found'])} "
            f"| {_percent(row['posed'])} |"
        )
    lines += ["", "By body (every frame):", ""]
    lines += ["| body | frames | found, ≥ 50 % | 30-50 % | < 30 % | time median (ms) |"]
    lines += ["| --- | ---: | ---: | ---: | ---: | ---: |"]
    for body, s in report["bodies"].items():
        cells = _band_cells(s["bands"])
        lines.append(f"| {body} | {s['frames']} | {cells} | {_ms(s['latency_ms_median'])} |")
    b, e = report["baseline"], report["engine_on_baseline_frames"]
    lines += [
        "",
        "### Baseline: FPFH + RANSAC + ICP told the right parts (pose only)",
        "",
        "Open3D's pipeline (`evaluation/baselines/fpfh.py`, `locate_instances`) on the first"
        f" {plan['baseline_frames']} unseen scene and bin frames, told each registered part the"
        " frame holds and how many of it: the frame thinned to the part's voxel (4 mm at"
        " least), its large planes set aside, then per instance RANSAC on FPFH matches and"
        " point-to-plane ICP, the points it explains taken out before the next. Found: a pose"
        " within ADD-S < 0.1 of an instance. The engine's figures on the same frames beside it,"
        " told nothing, and told the parts (`candidates`, not how many of each).",
        "",
        "| system | frames | instances | found, ≥ 50 % visible | 30-50 % | < 30 % | median ADD-S"
        " | time median / p95 (ms) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    systems = [("FPFH + RANSAC + ICP (told the parts)", b), ("engine (`/detect`)", e)]
    if report["engine_told_on_baseline_frames"]["frames"]:
        told = report["engine_told_on_baseline_frames"]
        systems.append(("engine told the parts (`candidates`)", told))
    for name, s in systems:
        add_s = "n/a" if s["median_add_s"] is None else f"{s['median_add_s']:.4f}"
        lines.append(
            f"| {name} | {s['frames']} | {s['instances']} | {_band_cells(s['bands'])} | {add_s}"
            f" | {_ms(s['latency_ms_median'])} / {_ms(s['latency_ms_p95'])} |"
        )
    lines += told_lines(report["told"])
    lines += real_lines(frames.get("real", []))
    lines += ["", "Raw figures (every frame, instance and detection) are in `frames.json`.", ""]
    return lines


def told_lines(told: dict) -> list[str]:
    """The table of the unseen scene and bin frames posted again with ``candidates``: the
    registered parts each holds, as a cell that knows what it loaded says."""
    if not told:
        return []
    lines = [
        "",
        "### Told the parts (`candidates`)",
        "",
        "The unseen scene and bin frames (640 × 480) posted again as organized PCDs with"
        " `candidates`: the registered parts each frame holds (not how many), as a bin-picking"
        " cell that knows what it loaded would send them. Beside it, the same frames as first"
        " posted (told nothing; a quarter of them as depth PNGs).",
        "",
        "| frames | told | frames | found, ≥ 50 % visible | 30-50 % | < 30 % | precision |"
        " wrong (duplicate / pose / label / unregistered / nothing) | time median (ms) |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | ---: |",
    ]
    for family, pair in told.items():
        for name in ("untold", "told"):
            s = pair[name]
            wrong = " / ".join(str(s["wrong_matches"][k]) for k in WRONG_KINDS)
            lines.append(
                f"| {family}, unseen | {'candidates' if name == 'told' else 'nothing'} |"
                f" {s['frames']} | {_band_cells(s['bands'])} | {_percent(s['precision'])} |"
                f" {wrong} | {_ms(s['latency_ms_median'])} |"
            )
    return lines


def real_lines(records: list[dict]) -> list[str]:
    """The table of the real frames (``evaluation.real_frames``)."""
    if not records:
        return []
    lines = [
        "",
        "### Real frames",
        "",
        "Real depth frames from public robotics data (`evaluation/real_frames.py`), posted as"
        " their drivers wrote them to the same server, each with its part's model registered;"
        " the part's detection (its best by confidence) against its reference pose where one is"
        " known. `pcl-milk` is shipped (tests/data/real/pcl-milk, BSD); the others are read"
        " from local copies when given (`--ycb`, `--apc`).",
        "",
        "| frame | sensor | part | verdict (confidence) | ADD-S | rotation error (°) | other"
        ' "match" | points | time (ms) |',
        "| --- | --- | --- | --- | ---: | ---: | --- | ---: | ---: |",
    ]
    for r in records:
        verdict = r.get("verdict") or ("error" if r.get("error") else "not detected")
        if r.get("confidence") is not None:
            verdict += f" ({r['confidence']:.2f})"
        add_s = "n/a" if r.get("add_s") is None else f"{r['add_s']:.4f}"
        angle = "n/a" if r.get("rotation_error_deg") is None else f"{r['rotation_error_deg']:.1f}"
        sensor = r["sensor"].split(",")[0].split(" (")[0]
        lines.append(
            f"| {r['frame']} | {sensor} | {r['label']} | {verdict} | {add_s} | {angle} "
            f"| {', '.join(r.get('other_matches') or []) or 'none'} | {r.get('num_points', 'n/a')}"
            f" | {_ms(r.get('latency_ms'))} |"
        )
    return lines
