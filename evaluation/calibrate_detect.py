"""Fit the confidence of ``POST /detect``'s detections (``service.engine.scene``) on whole
frames, and check it on frames of parts it was not fitted on.

    python -m evaluation.calibrate_detect                       # models/detect_confidence.json
    python -m evaluation.calibrate_detect --frames 4 --out /tmp/d.json   # a try
    python -m evaluation.calibrate_detect --told    # frames told their parts, added beside it

A part seen in a whole frame is often half hidden by others, and far smaller in the camera's
view than the single views ``evaluation.calibrate`` fits the chain's confidence on: the chain
then doubts instances that the frame shows clearly (their missing surface is hidden by a part
in front of it, not absent). The detection's confidence is a logistic regression over what
the frame says of an instance (``scene.evidence``: the chain's confidence, fit, coverage, the
margin, the share of what the camera should see that its depth shows, the share it saw through,
the share of its segment it explains, its points). A second one is fitted on the instances
that may be a match at all (``fit_scene``): it decides their confidence, and so the verdict.

Frames (``evaluation.frames``: scene, bin and foreign families) are drawn with one seed for
fitting, their registered parts from the manifest's seen objects, and with another for checking,
from the unseen ones; every part of the manifest but the foreign ones is registered, rescaled as
the frames hold it (a gallery of 52). Every instance ``Engine.detect`` finds with no floor is
kept with its evidence and whether it was right: the right part, ADD-S < 0.1 of its diameter,
matched one to one with the ground truth.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from tqdm import tqdm

from evaluation import frames as whole
from evaluation.calibrate import PRECISION, fit_calibration, judge
from evaluation.evaluate_mapping import checked
from evaluation.metrics import add_s, diameter
from service.api.clouds import organized
from service.engine.confidence import (
    ELIGIBLE_FEATURES,
    SCENE_FEATURES,
    SETTLED_FEATURES,
    Calibration,
    meets,
)
from service.engine.engine import Engine
from service.engine.frame import Frame
from service.engine.mapping import Mapper
from service.engine.sampling import sample_surface, sample_surface_faces
from service.engine.scene import match_floors, may_match
from service.engine.tuning import CHAIN_AGREES, MATCH_POINTS
from service.settings import MODELS_DIR, Settings

FAMILIES = {"scene": 3, "bin": 1, "foreign": 1}  # frames of each, per --frames
ADD_S_POINTS = 4096
ACCEPT_FLOOR = 0.5  # an instance is accepted when more likely right than not, at least
ELIGIBLE_EACH = 10  # the instances that may be a match get their own fit with this many of each


def gallery_engine(parts: list[whole.FramePart]) -> Engine:
    """An engine with every part registered from its rescaled mesh and checked as ``POST
    /references`` checks it, its look-alikes named: the chain's calibration, no scene
    calibration (an instance's confidence is the chain's)."""
    settings = Settings()
    chain = Calibration.load(settings.confidence_path)
    engine = Engine(Mapper.from_settings(settings.model), settings.engine, chain)
    references = []
    for part in tqdm(parts, desc="register", leave=False):
        points, faces = sample_surface_faces(part.mesh, 2048, 0)
        references.append(
            engine.make_reference(part.name, points, mesh=part.mesh, face_index=faces)
        )
    engine.load(references)
    # an instance its look-alikes fit alike is never a match: a gallery without them named
    # had its threshold set by them (docs/decisions.md#detections-counted-as-served)
    checked(engine, [part.name for part in parts], {part.name: part.mesh for part in parts})
    return engine


def frame_of(frame: whole.Frame) -> Frame:
    """The engine's view of a frame, as POST /detect makes it from its organized PCD."""
    grid = frame.points()
    cloud = organized(grid, grid.shape[0] * grid.shape[1], "frame")
    return Frame.of(cloud.points, cloud.index, cloud.shape)


def rows_of(
    engine: Engine, frame: whole.Frame, truth_points: dict, told: bool = False
) -> list[dict]:
    """Each instance found in ``frame`` (no floor, the chain's confidence; ``told``: with the
    registered parts it holds as the candidates): its evidence, and whether it was right,
    matched one to one, best first, with the ground truth."""
    named = frame.registered_parts() if told else None
    scene = engine.detect(frame_of(frame), candidates=named or None, floor=0.0)
    used: set[int] = set()
    rows = []
    for detection in scene.detections:
        answer, evidence = detection.answer, detection.evidence
        points = truth_points.get(answer.label)
        best, value = None, np.inf
        for k, instance in enumerate(frame.instances):
            if instance.name != answer.label or k in used or points is None:
                continue
            error = add_s(
                points,
                answer.rotation,
                answer.translation,
                instance.rotation,
                instance.translation,
                diameter(points),
            )
            if error < value:
                best, value = k, error
        right = best is not None and value < 0.1
        if right:
            used.add(best)
        rows.append({**evidence, "right": bool(right), "label": answer.label,
                     "family": frame.family, "frame": frame.stem,
                     "doubted": bool(answer.look_alikes)})  # fmt: skip
    return rows


def collect(
    engine, family_counts, seed, pool, foreign, truth_points, desc, told=False
) -> list[dict]:
    rows = []
    plan = [(family, i) for family, count in family_counts.items() for i in range(count)]
    for family, index in tqdm(plan, desc=desc, leave=False):
        frame = whole.make_frame(family, index, seed, pool, foreign)
        rows += rows_of(engine, frame, truth_points, told)
    return rows


def fit_scene(rows: list[dict], more: tuple[str, ...] = ()) -> Calibration:
    """The detection's calibration: a logistic regression on every instance, and one on those
    that may be a match alone, which judges them; each on ``more`` features as well. Most
    instances are plainly wrong (the chain refuses them, or they explain a few points):
    fitted on them all, the weights are set where nothing is decided, and the threshold by the
    few wrong ones that look right (docs/decisions.md#detect)."""
    calibration = fit_calibration(rows, SCENE_FEATURES + more)
    floors = match_floors()
    mine = [row for row in rows if meets(row, floors)]
    right = sum(row["right"] for row in mine)
    if min(right, len(mine) - right) < ELIGIBLE_EACH:  # too few to fit apart
        return calibration
    eligible = fit_calibration(mine, ELIGIBLE_FEATURES + more)
    return replace(calibration, eligible=eligible, eligible_at=floors)


def fitted(rows: list[dict], check: list[dict], more: tuple[str, ...] = ()) -> Calibration:
    """``fit_scene`` on ``rows``, its threshold by ``acceptance`` on ``rows`` and ``check``
    together, and how it does on each (``about``): on 200 frames one or two wrong instances
    set the threshold (docs/decisions.md#what-is-left-around)."""
    calibration = fit_scene(rows, more)
    accept = acceptance(calibration, rows + check)
    about = {
        "fit": judge(calibration, rows, accept),
        "check": judge(calibration, check, accept),
        "served": {
            "fit": served_figures(calibration, rows, accept),
            "check": served_figures(calibration, check, accept),
        },
    }
    return replace(calibration, accept=accept, about=about)


def served(calibration: Calibration, rows: list[dict], threshold: float) -> np.ndarray:
    """Which of ``rows`` ``Scan.judge`` makes a "match" at ``threshold``: ``may_match``, the
    points a match needs (those the evidence counts in its segment), and no look-alike fitting
    alike (``look_alikes.doubt``)."""
    scores = [calibration.confidence(row) for row in rows]
    return np.array(
        [row["points"] >= np.log10(MATCH_POINTS) and may_match(row, score, threshold)
         and not row.get("doubted")
         for row, score in zip(rows, scores, strict=True)], dtype=bool,
    )  # fmt: skip


def acceptance(calibration: Calibration, rows: list[dict]) -> float:
    """The lowest threshold, at least ``ACCEPT_FLOOR``, at which ``PRECISION`` of the
    instances the service would accept (``served``) are right."""
    right = np.array([row["right"] for row in rows], dtype=bool)
    for threshold in np.arange(ACCEPT_FLOOR, 0.995, 0.01):
        accepted = served(calibration, rows, threshold)
        if accepted.any() and right[accepted].mean() >= PRECISION:
            return round(float(threshold), 2)
    return 0.99


def served_figures(calibration: Calibration, rows: list[dict], threshold: float) -> dict:
    """Per family: the right instances, the share of them the service accepts, and the
    wrong ones it accepts."""
    accepted = served(calibration, rows, threshold)
    right = np.array([row["right"] for row in rows], dtype=bool)
    figures = {}
    for family in sorted({row["family"] for row in rows}):
        mine = np.array([row["family"] == family for row in rows])
        count = int((right & mine).sum())
        figures[family] = {
            "right": count,
            "right_accepted": float((accepted & right & mine).sum() / count) if count else None,
            "wrong_accepted": int((accepted & ~right & mine).sum()),
        }
    return figures


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m evaluation.calibrate_detect")
    parser.add_argument("--out", type=Path, default=MODELS_DIR / "detect_confidence.json")
    parser.add_argument("--frames", type=int, default=8, help="scene frames x3, bin, foreign")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--rows", type=Path, default=None, help="also write every instance here")
    parser.add_argument(
        "--told",
        action="store_true",
        help="fit the calibration of frames told their parts (candidates) and add it to --out",
    )
    args = parser.parse_args(argv)
    began = time.perf_counter()
    registered, foreign = whole.manifest_parts()
    engine = gallery_engine(registered)
    truth_points = {
        p.name: sample_surface(p.mesh, ADD_S_POINTS, 1).astype(np.float64)
        for p in registered + foreign
    }
    counts = {family: n * args.frames for family, n in FAMILIES.items()}
    seen = [p for p in registered if p.split == "seen"]
    unseen = [p for p in registered if p.split == "unseen"]
    if args.told:  # scene and bin frames: a part-free frame names no candidate
        counts = {family: n for family, n in counts.items() if family != "foreign"}
    fit_rows = collect(
        engine, counts, args.seed, seen, foreign, truth_points, "fit frames", args.told
    )
    check_rows = collect(
        engine, counts, args.seed + 1, unseen, foreign, truth_points, "check frames", args.told
    )
    calibration = fitted(fit_rows, check_rows)
    # judged again once the frame is searched; told frames are not
    # (docs/decisions.md#what-is-left-around)
    settled = None if args.told else fitted(fit_rows, check_rows, SETTLED_FEATURES)
    about = {
        "fitted": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python -m evaluation.calibrate_detect"
        + f" --frames {args.frames}"
        + (" --told" if args.told else ""),
        "model_sha256": engine.mapper.model_hash,
        "fit_frames": {k: v for k, v in counts.items()},
        **calibration.about,
        "accept": calibration.accept,
        "eligible": {
            "at": calibration.eligible_at,
            "fit_instances": sum(calibration.is_eligible(row) for row in fit_rows),
        }
        if calibration.eligible is not None
        else None,
        "accept_rule": "the lowest threshold of 99.5 % precision on the fit and check frames "
        f"together of the instances the service accepts, at least {ACCEPT_FLOOR}: a match also "
        f"needs {MATCH_POINTS} points and the chain's own confidence at least {CHAIN_AGREES}",
        "seconds": round(time.perf_counter() - began, 1),
    }
    calibration = replace(calibration, about=about, settled=settled)
    if args.rows:
        args.rows.write_text(json.dumps({"fit": fit_rows, "check": check_rows}, default=float))
    if args.told:  # beside the calibration of frames told nothing, which stays as it is
        calibration = replace(Calibration.load(args.out), told=calibration)
    elif args.out.exists():  # a told one fitted on the same model is kept beside the new one
        told = Calibration.load(args.out).told
        if told is not None and told.about.get("model_sha256") == engine.mapper.model_hash:
            calibration = replace(calibration, told=told)
    calibration.save(args.out)
    for fit in (calibration, settled):
        for part in ("fit", "check") if fit is not None else ():
            name = "settled " if fit is settled else ""
            print(f"{name}{part} at {fit.accept}:", fit.about[part])
            print(f"{name}{part}, as served:", fit.about["served"][part])
    print(f"detection calibration written to {args.out} in {about['seconds']:.0f} s")
    return about


if __name__ == "__main__":
    main()
