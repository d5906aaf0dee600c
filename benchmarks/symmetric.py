"""The symmetric family on more draws than the evaluation's: how often the same surface, turned
by its part's symmetry, is answered as one pose, and why a group misses.

    python -m benchmarks.symmetric --seeds 0,1,2 --groups 3

For each seed, each part of ``evaluation.evaluate.SYMMETRIC_PARTS`` gets ``--groups`` poses,
each turned about the part's axis by its symmetry, as the evaluation's ``symmetric`` family
makes them (its full clouds and one camera's views of them; seed 0 with 2 groups is the
evaluation's own), answered in process on the evaluation's gallery, told the viewpoint. Per
group it prints the spread of the answered rotations (the largest angle between two,
``evaluation.metrics.symmetric_spread``), over every answer and over the ``"match"`` answers,
and for a group past ``--within`` degrees what parts its two farthest answers:

- ``representative``: two answers that the part's symmetry makes one pose, given as different
  matrices: the pose lies near where the canonical rule (the equivalent rotation nearest the
  identity) switches from one representative to another, and the answers fall either side;
- ``near-turn``: answers at different near-symmetric turns of the part (a flange turned by a
  notch's step, a shaft about its axis), each within ADD-S 0.1 of the truth;
- ``wrong``: an answer of another part, or at a pose ADD-S 0.1 or more from the truth;
- ``refinement``: answers a few degrees apart (under 10) at the same turn;

and whether those two answers both said that other poses fit alike (``ambiguous``): the
answer's own warning that the view does not tell them apart. Beside the spread, how far the
answers of the right part lie from the truth (up to the symmetry), full clouds and depth
views apart: a rule that answered one pose for one surface by ignoring what the view shows
would narrow the spread and widen these.

Needs the ``eval`` and ``train`` extras (pybullet's meshes).
"""

from __future__ import annotations

import argparse
import itertools
import json
from collections import Counter
from pathlib import Path

import numpy as np

from evaluation.cases import make_cases
from evaluation.evaluate import FOREIGN, REFERENCE_POINTS, SYMMETRIC_PARTS
from evaluation.evaluate_mapping import prepare_engine
from evaluation.metrics import geodesic_deg, succeeds, symmetric_spread
from service.engine.symmetry import Symmetry
from service.settings import MODELS_DIR
from training.objects import load_manifest, load_object_meshes

WITHIN_DEG = 2.0  # the target: answers for the same surface within this of each other
NEAR_TURN_DEG = 10.0  # answers farther apart than this (up to the symmetry) are other turns


def cause(first: dict, second: dict, symmetry: Symmetry) -> str:
    """Why two answers of one group of a part with this ``symmetry`` lie apart (module
    docstring)."""
    if not (first["right"] and second["right"]):
        return "wrong"
    if symmetry.distance_deg(first["rotation"], second["rotation"]) > NEAR_TURN_DEG:
        return "near-turn"
    if geodesic_deg(first["rotation"], second["rotation"]) > NEAR_TURN_DEG:
        return "representative"
    return "refinement"


def truth_figures(groups: list[dict]) -> dict[str, list[float]]:
    """Per kind of view (``full``, ``sensor``): the median and 95th percentile of the answers'
    angles from the truth, in degrees, and the share within ``WITHIN_DEG``."""
    figures = {}
    for view in ("full", "sensor"):
        angles = np.array(
            [
                a
                for g in groups
                if g["group"].endswith("/" + view)
                for a in g["truth_deg"]
                if a is not None
            ]
        )
        if not len(angles):
            figures[view] = [float("nan")] * 3
            continue
        figures[view] = [
            round(float(np.median(angles)), 2),
            round(float(np.percentile(angles, 95)), 2),
            round(float(np.mean(angles <= WITHIN_DEG)), 3),
        ]
    return figures


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.symmetric", description=__doc__)
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated")
    parser.add_argument("--groups", type=int, default=3, help="poses per part and seed")
    parser.add_argument("--within", type=float, default=WITHIN_DEG)
    parser.add_argument("--json", type=Path, default=None, help="also write every group here")
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]

    unseen = [s for s in load_manifest(split="unseen") if s.name not in FOREIGN]
    engine, _ = prepare_engine(MODELS_DIR / "dpc_mn.onnx", MODELS_DIR / "gallery.npz", unseen)
    meshes = load_object_meshes([s for s in load_manifest() if s.name in SYMMETRIC_PARTS])
    scales = {name: engine.entry(name).reference.scale for name in meshes}

    groups = []
    for seed in seeds:
        cases = make_cases(
            "symmetric", meshes, scales, REFERENCE_POINTS, seed, args.groups, orders=SYMMETRIC_PARTS
        )
        answers: dict[str, list[dict]] = {}
        for case in cases:
            seen_from = case.params.get("viewpoint")
            found = engine.align(
                case.points, viewpoint=None if seen_from is None else np.asarray(seen_from)
            )
            entry = engine.entry(case.object_name)
            labelled = found.label == case.object_name
            right = labelled and succeeds(
                entry.reference.points,
                found.rotation,
                found.translation,
                case.rotation,
                case.translation,
            )
            answers.setdefault(case.params["group"], []).append(
                {
                    "rotation": found.rotation,
                    "right": right,
                    "match": found.verdict == "match",
                    "ambiguous": found.ambiguous,
                    # how far from the truth, up to the symmetry (None: another part's answer)
                    "truth_deg": entry.symmetry.distance_deg(found.rotation, case.rotation)
                    if labelled
                    else None,
                }
            )
        for name, members in answers.items():
            symmetry = engine.entry(name.split("/")[0]).symmetry
            spread = symmetric_spread(m["rotation"] for m in members)
            matched = [m["rotation"] for m in members if m["match"]]
            farthest = max(
                itertools.combinations(members, 2),
                key=lambda pair: geodesic_deg(pair[0]["rotation"], pair[1]["rotation"]),
            )
            groups.append(
                {
                    "seed": seed,
                    "group": name,
                    "spread_deg": spread,
                    "spread_match_deg": symmetric_spread(matched) if len(matched) > 1 else 0.0,
                    "cause": cause(*farthest, symmetry) if spread > args.within else None,
                    # the two farthest answers both said other poses fit alike
                    "flagged": all(m["ambiguous"] for m in farthest),
                    "truth_deg": [m["truth_deg"] for m in members],
                }
            )
        print(f"seed {seed}: {len(answers)} groups answered", flush=True)

    missed = [g for g in groups if g["spread_deg"] > args.within]
    missed_match = [g for g in groups if g["spread_match_deg"] > args.within]
    print(f"\ngroups past {args.within} degrees (spread of every answer / of the matches):")
    for g in missed:
        print(
            f"  seed {g['seed']} {g['group']:24s} {g['spread_deg']:6.1f} / "
            f"{g['spread_match_deg']:6.1f}  {g['cause']}{', ambiguous' if g['flagged'] else ''}"
        )
    summary = {
        "groups": len(groups),
        "within": len(groups) - len(missed),
        "within_match": len(groups) - len(missed_match),
        "causes": dict(Counter(g["cause"] for g in missed)),
        "flagged": sum(g["flagged"] for g in missed),
        # a rule could answer one pose for one surface and pose it worse: how far the answers
        # of the right part lie from the truth, up to the symmetry
        "truth_deg": truth_figures(groups),
    }
    print(
        f"\n{summary['within']} of {summary['groups']} groups within {args.within} degrees "
        f"({summary['within_match']} among the matches); misses by cause: {summary['causes']}; "
        f"{summary['flagged']} of the misses' two farthest answers both flagged ambiguous"
    )
    truth = summary["truth_deg"]
    print(
        "answers of the right part from the truth (up to the symmetry), median / 95th "
        f"percentile / share within {WITHIN_DEG} degrees: full clouds {truth['full']}, "
        f"depth views {truth['sensor']}"
    )
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "groups": groups}, indent=2))
    return summary


if __name__ == "__main__":
    main()
