"""The evaluation's report: tables, plots, the targets, README.md and results.json.

Everything here is computed from the records of ``evaluation.evaluate``; the README is written by
``write_report`` and never edited by hand. ``python -m evaluation.report results.json`` rewrites
the README and the plots from a run's raw figures.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from evaluation.cases import FAMILIES  # noqa: E402
from evaluation.metrics import ADD_S_POINTS, PRECISE_ADD_S, SUCCESS_ADD_S, summarize  # noqa: E402
from evaluation.report_answers import answers_report, plot_reliability, readme_lines  # noqa: E402
from evaluation.report_frames import frames_report, write_plots  # noqa: E402
from evaluation.report_frames import readme_lines as frames_lines  # noqa: E402

SETS = ("seen", "unseen")
BASELINE_NAMES = {"ppf": "PPF (OpenCV)", "fpfh": "FPFH + RANSAC + ICP (Open3D)"}
VISIBLE_BINS = (0.0, 0.3, 0.4, 0.5, 0.6, 1.0)
PLOTS = {
    "sparse": "fig5_accuracy_vs_points_kept.png",
    "poses": "fig6_alignment_error_per_pose.png",
    "noise": "success_vs_noise.png",
    "visible": "success_vs_visible_share.png",
    "latency": "latency.png",
    "reliability": "reliability.png",
}
POSE_FAMILIES = tuple(f for f in FAMILIES if f not in ("foreign", "junk"))  # a pose to measure
TABLE_STUDIES = {  # the studies with per-family tables, and their object sets
    "side-by-side": SETS,
    "sensor-side-by-side": (*SETS, "all"),
    "full-gallery": SETS,
}
# The targets, on seen objects with refinement (the full-gallery engine).
TARGET_PRECISE = 0.95
TARGET_FLOOR_GAP = 0.005
TARGET_SPARSE_ACCURACY = 0.95
TARGET_SUCCESS = 0.95
TARGET_PARTIAL_SUCCESS = 0.80
TARGET_SPEEDUP = 100.0


def select(records: list[dict], **where) -> list[dict]:
    return [r for r in records if all(r.get(k) == v for k, v in where.items())]


def summaries(records: list[dict]) -> dict:
    """study -> system -> family -> set ("all" too) -> summarize(...)."""
    grouped: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(dict)))
    keys = {(r["study"], r["system"], r["family"]) for r in records}
    for study, system, family in sorted(keys):
        rows = select(records, study=study, system=system, family=family)
        for split in SETS:
            chosen = select(rows, set=split)
            if chosen:
                grouped[study][system][family][split] = summarize(chosen)
        grouped[study][system][family]["all"] = summarize(rows)
    return json.loads(json.dumps(grouped))


def by_value(records: list[dict], key: str) -> dict[float, dict]:
    """summarize() per distinct value of ``key`` (keep_share, noise_share)."""
    values = sorted({r[key] for r in records if r.get(key) is not None})
    return {v: summarize([r for r in records if r.get(key) == v]) for v in values}


def by_visible_share(records: list[dict]) -> list[dict]:
    rows = []
    for low, high in zip(VISIBLE_BINS[:-1], VISIBLE_BINS[1:], strict=True):
        chosen = [r for r in records if low <= r.get("visible_share", -1) < high]
        if chosen:
            rows.append({"low": low, "high": high, **summarize(chosen)})
    return rows


def curves(records: list[dict]) -> dict:
    """The figures behind the plots."""
    result: dict = {"sparse": {}, "noise": {}, "visible": {}}
    for study in ("side-by-side", "full-gallery"):
        for system in sorted({r["system"] for r in select(records, study=study)}):
            rows = select(records, study=study, system=system, family="sparse")
            for split in (*SETS, "all"):
                chosen = rows if split == "all" else select(rows, set=split)
                if chosen:
                    result["sparse"][f"{study}/{system}/{split}"] = by_value(chosen, "keep_share")
            partial = select(records, study=study, system=system, family="partial")
            if partial:
                result["visible"][f"{study}/{system}"] = by_visible_share(partial)
    for study in ("noise", "noise-full-gallery"):
        for system in sorted({r["system"] for r in select(records, study=study)}):
            rows = select(records, study=study, system=system)
            result["noise"][f"{study}/{system}"] = by_value(rows, "noise_share")
    return json.loads(json.dumps(result))


# --- targets ---------------------------------------------------------------------------------


def _figure(value: float, percent: bool = True) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{100 * value:.1f} %" if percent else f"{value:.4f}"


def targets(records: list[dict], table: dict) -> list[dict]:
    """Each target of the brief: met or missed, with its figure."""
    seen = table.get("full-gallery", {}).get("engine", {})

    def get(family: str, key: str) -> float:
        return seen.get(family, {}).get("seen", {}).get(key, float("nan"))

    rows = []

    def add(name: str, figure: str, met: bool) -> None:
        rows.append({"target": name, "figure": figure, "met": bool(met)})

    accuracy = get("paper-poses", "accuracy")
    add("paper-poses: recognition 100 %", _figure(accuracy), accuracy == 1.0)
    precise = get("paper-poses", "precise")
    add("paper-poses: precise ≥ 95 %", _figure(precise), precise >= TARGET_PRECISE)
    error, floor = (
        get("paper-poses", "median_align_err"),
        get("paper-poses", "median_align_err_floor"),
    )
    add(
        "paper-poses: median normalised alignment error within 0.005 of its floor",
        f"{error:.4f} against a floor of {floor:.4f} (gap {error - floor:+.4f})",
        error - floor <= TARGET_FLOOR_GAP,
    )
    sparse = select(records, study="full-gallery", system="engine", family="sparse", set="seen")
    tenth = summarize([r for r in sparse if r.get("keep_share") == 0.1])
    add(
        "sparse at 10 %: recognition ≥ 95 %",
        _figure(tenth.get("accuracy", float("nan"))),
        tenth.get("accuracy", 0.0) >= TARGET_SPARSE_ACCURACY,
    )
    for family in ("so3", "noisy"):
        success = get(family, "success")
        add(f"{family}: success ≥ 95 %", _figure(success), success >= TARGET_SUCCESS)
    success = get("partial", "success")
    add("partial: success ≥ 80 %", _figure(success), success >= TARGET_PARTIAL_SUCCESS)

    side = select(records, study="side-by-side")
    engine = summarize(select(side, system="engine"))
    baselines = {b: summarize(select(side, system=b)) for b in BASELINE_NAMES}
    baselines = {b: s for b, s in baselines.items() if s.get("cases")}
    if engine.get("cases") and baselines:
        faster = min(baselines, key=lambda b: baselines[b]["latency_ms_median"])
        other = baselines[faster]
        speedup = other["latency_ms_median"] / engine["latency_ms_median"]
        add(
            "median latency ≥ 100× lower than the faster baseline at equal or better success",
            f"engine {engine['latency_ms_median']:.0f} ms (success {_figure(engine['success'])})"
            f" against {faster} {other['latency_ms_median']:.0f} ms"
            f" (success {_figure(other['success'])}): {speedup:.0f}× lower",
            speedup >= TARGET_SPEEDUP and engine["success"] >= other["success"],
        )
    return rows


# --- plots -----------------------------------------------------------------------------------

STYLE = {"engine": "C0", "engine-no-refine": "C4", "ppf": "C1", "fpfh": "C2"}


def _label(system: str) -> str:
    return BASELINE_NAMES.get(system, system)


def plot_sparse(data: dict, path: Path) -> None:
    figure, axis = plt.subplots(figsize=(6.4, 4.2))
    for key, points in data.items():
        study, system, split = key.split("/")
        if study == "side-by-side" and split == "all" and system in ("engine", *BASELINE_NAMES):
            style = {"color": STYLE[system], "marker": "o"}
            label = f"{_label(system)} (side-by-side gallery)"
        elif study == "full-gallery" and system == "engine" and split in SETS:
            style = {"color": "C0", "linestyle": "--" if split == "seen" else ":", "marker": "s"}
            label = f"engine, full gallery, {split}"
        else:
            continue
        shares = [float(s) for s in points]
        axis.plot(shares, [p["accuracy"] for p in points.values()], label=label, **style)
    axis.set(xlabel="share of the points kept", ylabel="recognition accuracy", ylim=(0, 1.05))
    axis.set_title("Recognition against the share of points kept (paper's Fig. 5)")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_poses(records: list[dict], path: Path) -> None:
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for axis, split in zip(axes, SETS, strict=True):
        for system, color in (("engine", "C0"), ("engine-no-refine", "C4")):
            rows = select(
                records, study="full-gallery", system=system, family="paper-poses", set=split
            )
            per_pose = defaultdict(list)
            floor = defaultdict(list)
            for r in rows:
                if r["align_err"] is not None:
                    per_pose[r["pose_index"]].append(r["align_err"])
                floor[r["pose_index"]].append(r["align_err_floor"])
            poses = sorted(per_pose)
            label = "refinement on" if system == "engine" else "refinement off"
            axis.plot(poses, [np.mean(per_pose[p]) for p in poses], ".", color=color, label=label)
            if system == "engine":
                poses = sorted(floor)
                axis.plot(
                    poses, [np.mean(floor[p]) for p in poses], "_", color="k",
                    label="floor (true pose)",
                )  # fmt: skip
        axis.set(xlabel="paper pose index (0-124)", title=f"{split} objects", yscale="log")
        axis.set_xlim(-2, 126)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    axes[0].set_ylabel("normalised alignment error (mean over objects)")
    figure.suptitle("Alignment error per paper pose (paper's Fig. 6), full gallery")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_noise(data: dict, path: Path) -> None:
    figure, axis = plt.subplots(figsize=(6.4, 4.2))
    for key, points in data.items():
        study, system = key.split("/")
        full = study == "noise-full-gallery"
        label = f"{_label(system)} ({'full gallery' if full else 'side-by-side gallery'})"
        shares = [100 * float(s) for s in points]
        style = {"color": STYLE.get(system, "C3"), "linestyle": "--" if full else "-"}
        axis.plot(shares, [p["success"] for p in points.values()], marker="o", label=label, **style)
    axis.set(xlabel="noise σ (% of the scale)", ylabel="success (ADD-S < 0.10)", ylim=(0, 1.05))
    axis.set_title("Success against noise (so3 cases)")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_visible(data: dict, path: Path) -> None:
    figure, axis = plt.subplots(figsize=(6.4, 4.2))
    for key, bins in data.items():
        study, system = key.split("/")
        if system not in ("engine", *BASELINE_NAMES):
            continue
        full = study == "full-gallery"
        centres = [(b["low"] + b["high"]) / 2 for b in bins]
        style = {"color": STYLE[system], "linestyle": "--" if full else "-"}
        label = f"{_label(system)} ({'full gallery' if full else 'side-by-side gallery'})"
        axis.plot(centres, [b["success"] for b in bins], marker="o", label=label, **style)
    axis.set(xlabel="visible share of the surface", ylabel="success (ADD-S < 0.10)")
    axis.set(xlim=(0, 1), ylim=(0, 1.05), title="Success against the visible share (partial cases)")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def latency_rows(records: list[dict], http: dict | None) -> list[dict]:
    rows = []
    for study in TABLE_STUDIES:
        for system in dict.fromkeys(r["system"] for r in select(records, study=study)):
            s = summarize(select(records, study=study, system=system))
            rows.append(
                {
                    "system": system,
                    "study": study,
                    "how": "in-process",
                    "cases": s["cases"],
                    "median": s["latency_ms_median"],
                    "p95": s["latency_ms_p95"],
                }
            )
    if http:
        rows.append(
            {
                "system": "engine",
                "study": f"full-gallery ({http['references']} references)",
                "how": "HTTP, raw float32 body",
                "cases": http["cases"],
                "median": http["latency_ms_median"],
                "p95": http["latency_ms_p95"],
            }
        )
    return rows


def plot_latency(rows: list[dict], path: Path) -> None:
    figure, axis = plt.subplots(figsize=(8, 0.45 * len(rows) + 1.5))
    names = [f"{_label(r['system'])} [{r['study']}, {r['how']}]" for r in rows]
    y = np.arange(len(rows))
    axis.barh(y, [r["median"] for r in rows], color="C0", label="median")
    axis.plot([r["p95"] for r in rows], y, "k|", markersize=12, label="95th percentile")
    axis.set(yticks=y, xscale="log", xlabel="latency per query (ms, log scale)")
    axis.set_yticklabels(names, fontsize=7)
    axis.invert_yaxis()
    axis.grid(alpha=0.3, axis="x")
    axis.legend(fontsize=7)
    axis.set_title("Latency per system")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


# --- the README ------------------------------------------------------------------------------


def _ms(value: float) -> str:
    return "n/a" if value is None or math.isnan(value) else f"{value:,.0f}"


def family_table(table: dict, study: str, family: str, split: str) -> list[str]:
    lines = [
        "| system | cases | accuracy | success | precise | median rot. err. (°) | median ADD-S "
        "| median align. err. (floor) | latency median / p95 (ms) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for system, families in table.get(study, {}).items():
        s = families.get(family, {}).get(split)
        if not s:
            continue
        lines.append(
            f"| {_label(system)} | {s['cases']} | {_figure(s['accuracy'])} "
            f"| {_figure(s['success'])} | {_figure(s['precise'])} "
            f"| {s['median_rot_err_deg']:.2f} | {s['median_add_s']:.4f} "
            f"| {s['median_align_err']:.4f} ({s['median_align_err_floor']:.4f}) "
            f"| {_ms(s['latency_ms_median'])} / {_ms(s['latency_ms_p95'])} |"
        )
    return lines


def baseline_settings() -> dict[str, dict]:
    settings = {}
    for system in BASELINE_NAMES:
        try:
            module = __import__(f"evaluation.baselines.{system}", fromlist=["_"])
        except ImportError:
            continue
        settings[system] = {
            k: getattr(module, k)
            for k in dir(module)
            if k.isupper() and isinstance(getattr(module, k), (int, float))
        }
    return settings


def curve_tables(data: dict) -> list[str]:
    """The figures behind the Fig. 5, noise and visible-share plots, as tables."""
    lines = ["## Against the share kept, the noise and the visible share", ""]
    for title, key, metric, unit in (
        ("Recognition accuracy against the share of points kept (sparse)", "sparse", "accuracy", 1),
        ("Success against noise σ (% of the scale; so3 cases)", "noise", "success", 100),
    ):
        columns = sorted({float(v) for points in data[key].values() for v in points})
        lines += [f"{title}:", "", "| system | " + " | ".join(f"{unit * c:g}" for c in columns)]
        lines[-1] += " |"
        lines.append("| --- |" + " ---: |" * len(columns))
        for series, points in data[key].items():
            if series.startswith("side-by-side/") and not series.endswith("/all"):
                continue  # the small gallery: both sets together
            if series.startswith("full-gallery/") and series.endswith("/all"):
                continue  # the full gallery: seen and unseen apart
            values = {float(v): p for v, p in points.items()}
            cells = [
                f"{_figure(values[c][metric])} ({values[c]['cases']})" if c in values else ""
                for c in columns
            ]
            lines.append(f"| {series} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["Success against the visible share (partial cases, binned):", ""]
    lines += ["| system | bin | cases | success | accuracy |", "| --- | --- | ---: | ---: | ---: |"]
    for series, bins in data["visible"].items():
        for b in bins:
            lines.append(
                f"| {series} | {b['low']:.1f}-{b['high']:.1f} | {b['cases']} "
                f"| {_figure(b['success'])} | {_figure(b['accuracy'])} |"
            )
    lines += ["", "Cells: the figure (cases).", ""]
    return lines


def readme(
    result: dict,
    table: dict,
    goal_rows: list[dict],
    lat_rows: list[dict],
    data: dict,
    answers: dict,
) -> str:
    m = result["machine"]
    studies = result["studies"]
    lines = [
        "# Evaluation",
        "",
        f"Written by `{result['command']}` (seed {result['seed']}); do not edit by hand.",
        "",
        "## Machine and run",
        "",
        f"- date: {result['started_utc']}; the run took {result['seconds'] / 60:.1f} min",
        f"- machine: {m['platform']}, {m['cpus']} CPUs ({m['cpu_model']}), Python {m['python']};"
        f" load average at start {', '.join(f'{x:.1f}' for x in m['load_average_at_start'])}"
        " (other jobs share the machine: latencies include their contention)",
        f"- model: `{result['model']}` (sha256 {result['model_sha256'][:12]}…)",
        "",
        "What ran:",
        "",
    ]
    descriptions = {
        "full-gallery": "the engine and its ablations on the full gallery (every shipped seen"
        " object plus every unseen object registered at run time)",
        "side-by-side": "every system on the same small gallery (the engine restricted to it"
        " with `candidates`), the same cases",
        "sensor-side-by-side": "the engine (with and without the viewpoint) and the baselines on"
        " the same `sensor` views of a small gallery (the baselines take about a second per"
        " reference and query, which bounds the gallery)",
        "noise": "so3 cases at noise σ = 0, 0.5, 1, 2, 4 % of the scale, on the side-by-side"
        " gallery",
        "noise-full-gallery": "the same noise levels, the engine on the full gallery",
    }
    for name, study in studies.items():
        split_count = defaultdict(int)
        for obj in study["objects"]:
            split_count[result["splits"].get(obj, "kept out")] += 1  # foreign parts, junk
        families = ", ".join(f"{f} {n}" for f, n in study["cases_per_family"].items())
        seconds = result["seconds_per_study"].get(name, {})
        took = sum(v for k, v in seconds.items() if not k.endswith("_build"))
        lines.append(
            f"- **{name}**: {descriptions[name]}. Gallery of {len(study['gallery'])} references;"
            f" cases on {split_count['seen']} seen + {split_count['unseen']} unseen objects"
            f" (+ {split_count['kept out']} foreign parts and kinds of junk),"
            f" {study['cases']} cases ({families}); systems: {', '.join(study['systems'])};"
            f" {took / 60:.1f} min."
        )
    if result.get("http"):
        h = result["http"]
        lines.append(
            f"- **HTTP**: the default engine as `python -m service` holding {h['references']}"
            f" references, {h['cases']} so3 cases sent one at a time as raw float32 bodies to"
            f" `POST /align` (accuracy {_figure(h['accuracy'])})."
        )
    side_gallery = studies.get("side-by-side", {}).get("gallery", [])
    sensor_gallery = studies.get("sensor-side-by-side", {}).get("gallery", [])
    foreign = result.get("foreign", [])
    symmetric = sorted({r["object"] for r in result["records"] if r["family"] == "symmetric"})
    plan = defaultdict(int, result["plan"])  # a run from before a field was added: 0
    lines += [
        "",
        f"Side-by-side gallery: {', '.join(side_gallery)}. Per object: paper-poses"
        f" {plan['baseline_paper_poses']} pose(s), sparse {plan['baseline_sparse_poses']} pose(s)"
        f" × keep shares {list(plan['keep_shares'])}, so3 / noisy / partial"
        f" {plan['baseline_random_cases']} each. Full gallery, per object: paper-poses"
        f" {plan['paper_poses']}, sparse {plan['sparse_poses']} × the keep shares, so3 / noisy"
        f" {plan['random_cases']}, partial {plan['partial_cases']}, sensor"
        f" {plan['sensor_cases']}, units {plan['units_cases']} (a full cloud and a sensor view"
        f" each), table {plan['table_cases']}; foreign: {plan['foreign_cases']} full cloud(s) and"
        f" sensor view(s) of each of {', '.join(foreign) or 'none'} (unseen, kept out of the"
        f" gallery); junk {plan['junk_cases']} of each kind; symmetric"
        f" {plan['symmetric_groups']} pose(s) of each of {', '.join(symmetric) or 'none'}, each"
        f" turned about its axis. Sensor side-by-side gallery: {', '.join(sensor_gallery)},"
        f" {plan['sensor_side_cases']} sensor view(s) per object. The baselines take seconds per"
        " query against a few references, which is what bounds their gallery and cases.",
        "",
        "Systems: `engine` (the default: mapped + principal-axes hypotheses, ICP refinement,"
        " given the viewpoint of camera-frame clouds), `engine-no-viewpoint` (the same, never"
        " given it), `engine-no-refine` (refinement off), `engine-paper` (the paper's least"
        " squares + SVD over the mapped pairs alone), `engine-mapped` (mapped hypotheses alone),"
        " `engine-principal-axes` (principal axes alone); the ablations refine and run on the"
        " full clouds and sensor views. The baselines orient normals toward the camera where"
        " the case has one.",
        "",
        "Metrics as docs/evaluation-protocol.md:"
        f" success = right label and ADD-S < {SUCCESS_ADD_S};"
        f" precise = right label and ADD-S < {PRECISE_ADD_S}; ADD-S on {ADD_S_POINTS:,} points of"
        " the mesh (on the reference's 2,048 an answer that differs from the truth by a symmetry"
        " of the part scores 0.020-0.022, the sampling's floor, at the precise threshold; on"
        f" {ADD_S_POINTS:,}, under 0.01); the alignment error is measured on"
        " the reference the answer named, over the scale, with its floor (the true object at the"
        " true pose) in brackets. Latency is the wall time of one query in-process.",
        "",
        "## Targets (seen objects, full gallery, refinement on)",
        "",
        "| target | figure | |",
        "| --- | --- | --- |",
    ]
    for row in goal_rows:
        lines.append(f"| {row['target']} | {row['figure']} | {'met' if row['met'] else 'MISSED'} |")
    lines += ["", "## Plots", ""]
    for key, name in PLOTS.items():
        lines.append(f"![{key}]({name})")
        lines.append("")
    lines += curve_tables(data)
    lines += ["## Latency", "", "| system | gallery | how | cases | median (ms) | p95 (ms) |"]
    lines.append("| --- | --- | --- | ---: | ---: | ---: |")
    for r in lat_rows:
        lines.append(
            f"| {_label(r['system'])} | {r['study']} | {r['how']} | {r['cases']} "
            f"| {_ms(r['median'])} | {_ms(r['p95'])} |"
        )
    lines += [""] + readme_lines(answers)
    for study, splits in TABLE_STUDIES.items():
        lines += ["", f"## Tables: {study}", ""]
        for family in POSE_FAMILIES:
            for split in splits:
                table_lines = family_table(table, study, family, split)
                if len(table_lines) > 2:
                    lines += [f"### {family}, {split} objects", "", *table_lines, ""]
    lines += ["## Baseline settings", ""]
    for system, settings in baseline_settings().items():
        values = ", ".join(f"`{k}` = {v}" for k, v in settings.items())
        lines.append(f"- {_label(system)} (`evaluation/baselines/{system}.py`): {values}")
    lines += ["", "Raw figures (every case) are in `results.json`.", ""]
    return "\n".join(lines)


def write_report(result: dict, out: Path) -> None:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records = result["records"]
    table = summaries(records)
    data = curves(records)
    goal_rows = targets(records, table)
    lat_rows = latency_rows(records, result.get("http"))
    plot_sparse(data["sparse"], out / PLOTS["sparse"])
    plot_poses(records, out / PLOTS["poses"])
    plot_noise(data["noise"], out / PLOTS["noise"])
    plot_visible(data["visible"], out / PLOTS["visible"])
    plot_latency(lat_rows, out / PLOTS["latency"])
    answers = answers_report(records)
    plot_reliability(answers["calibration"], out / PLOTS["reliability"])
    document = {
        **{k: v for k, v in result.items() if k != "records"},
        "summaries": table,
        "curves": data,
        "targets": goal_rows,
        "latency": lat_rows,
        "answers": answers,
        "baseline_settings": baseline_settings(),
        "records": records,
    }
    frames = result.get("frames")  # the whole-frame study, kept in its own frames.json
    if frames is None and (out / "frames.json").exists():
        frames = json.loads((out / "frames.json").read_text())
    elif frames is not None:
        (out / "frames.json").write_text(json.dumps(frames, indent=1, default=_plain) + "\n")
    document.pop("frames", None)
    (out / "results.json").write_text(json.dumps(document, indent=1, default=_plain) + "\n")
    text = readme(result, table, goal_rows, lat_rows, data, answers)
    if frames is not None:
        frame_figures = frames_report(frames)
        write_plots(frames, frame_figures, out)
        text = text.rstrip("\n") + "\n\n" + "\n".join(frames_lines(frames, frame_figures))
    (out / "README.md").write_text(text)


def main(argv: list[str] | None = None) -> None:
    """Rewrite the report (README and plots) from a results.json, without running anything."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("results", type=Path, help="a results.json of evaluation.evaluate")
    parser.add_argument("--out", type=Path, default=None, help="default: the results' folder")
    args = parser.parse_args(argv)
    result = json.loads(args.results.read_text())
    write_report(result, args.out or args.results.parent)


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot write {type(value)} to JSON")


if __name__ == "__main__":
    main()
