"""``--accuracy``: success shares over HTTP on the evaluation's cases of pybullet's meshes (the
``train`` extra), seen objects in the shipped gallery and unseen ones registered through the API.
"""

from __future__ import annotations

import argparse
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import httpx
import numpy as np
import orjson

from benchmarks.align_http.clouds import CLOUD_POINTS, JSON_TYPE, RAW_TYPE
from benchmarks.align_http.timing import serve
from evaluation.latency import latency_stats
from evaluation.metrics import SUCCESS_ADD_S, add_s, diameter
from evaluation.served import seed_store
from service.engine.reference import Reference

ACCURACY_FAMILIES = ("paper-poses", "so3", "sparse")


def accuracy(
    args: argparse.Namespace,
    gallery_refs: list[Reference],
    model_hash: str,
    workdir: Path,
) -> dict:
    """Success (right label, ADD-S < 0.10) per family on seen and on unseen objects, on the
    evaluation's cases of pybullet's meshes (the train extra)."""
    from evaluation.cases import make_cases
    from service.engine.sampling import sample_surface
    from training.objects import load_manifest, load_object_meshes

    seen_specs = load_manifest(split="seen")
    unseen_specs = load_manifest(split="unseen")
    in_gallery = {r.name for r in gallery_refs}
    seen_meshes = load_object_meshes([s for s in seen_specs if s.name in in_gallery])
    unseen_meshes = load_object_meshes([s for s in unseen_specs if s.name not in in_gallery])
    data_dir = workdir / "data-accuracy"
    seed_store(data_dir, gallery_refs, model_hash)
    models = {
        name: sample_surface(mesh, CLOUD_POINTS, 0)  # as the shipped gallery sampled them
        for name, mesh in {**seen_meshes, **unseen_meshes}.items()
    }
    print(f"[accuracy] starting the service with {len(gallery_refs)} references", flush=True)
    result: dict = {"poses_per_object": args.accuracy_poses, "seed": args.seed}
    with (
        serve(data_dir, args, "cpu") as service,
        httpx.Client(base_url=service.url, timeout=300.0) as client,
    ):
        register_ms = []
        for name in unseen_meshes:
            body = orjson.dumps({"name": name, "points": models[name].tolist()})
            began = time.perf_counter()
            answer = client.post(
                "/references", params={"self_check": "false"}, content=body, headers=JSON_TYPE
            )
            register_ms.append((time.perf_counter() - began) * 1e3)
            if answer.status_code != 201:
                raise RuntimeError(f"registering {name} failed: {answer.text}")
        result["gallery_references"] = client.get("/health").json()["references"]
        result["unseen_registration_ms"] = latency_stats(register_ms) if register_ms else None
        for split, meshes in (("seen", seen_meshes), ("unseen", unseen_meshes)):
            scales = {name: float(_radius(models[name])) for name in meshes}
            diameters = {name: diameter(models[name]) for name in meshes}
            for family in ACCURACY_FAMILIES:
                cases = make_cases(
                    family,
                    meshes,
                    scales,
                    n_points=CLOUD_POINTS,
                    seed=args.seed,
                    poses_per_object=args.accuracy_poses,
                )
                print(f"[accuracy] {split} {family}: {len(cases)} cases", flush=True)

                with ThreadPoolExecutor(args.accuracy_clients) as pool:
                    outcomes = list(
                        pool.map(partial(judge, client, models=models, diameters=diameters), cases)
                    )
                labels = np.array([o[0] for o in outcomes])
                successes = np.array([o[1] for o in outcomes])
                errors = np.array([o[2] for o in outcomes])
                result[f"{split}/{family}"] = {
                    "cases": len(cases),
                    "objects": len(meshes),
                    "recognition": float(labels.mean()),
                    "success": float(successes.mean()),
                    "median_add_s": float(np.median(errors)),
                }
                if family == "sparse":  # the paper's Fig. 5: success against the share kept
                    shares = np.array([case.params["keep_share"] for case in cases])
                    result[f"{split}/{family}"]["success_by_keep_share"] = {
                        f"{share:g}": float(successes[shares == share].mean())
                        for share in sorted(set(shares.tolist()))
                    }
    shutil.rmtree(data_dir, ignore_errors=True)
    return result


def judge(client: httpx.Client, case, models: dict, diameters: dict) -> tuple[bool, bool, float]:
    """Align one case over HTTP: whether the label is right, whether it succeeds, its ADD-S."""
    answer = client.post(
        "/align", content=np.asarray(case.points, "<f4").tobytes(), headers=RAW_TYPE
    )
    if answer.status_code != 200:
        raise RuntimeError(f"/align answered {answer.status_code}: {answer.text[:300]}")
    body = answer.json()
    label_ok = body["label"] == case.object_name
    error = add_s(
        models[case.object_name],
        np.array(body["rotation"]),
        np.array(body["translation"]),
        case.rotation,
        case.translation,
        diameters[case.object_name],
    )
    return label_ok, label_ok and error < SUCCESS_ADD_S, error


def _radius(points: np.ndarray) -> float:
    points = np.asarray(points, dtype=np.float64)
    return float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())
