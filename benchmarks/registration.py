"""Where a registration's seconds go, and what a batch of parts costs.

``python -m benchmarks.registration [--parts 6] [--skip-http] [--json out.json]``

1. In process, the shipped model, settings and gallery (45 references): each part of the object
   manifest (unseen first) as its mesh and as its 2,048 sampled points (a cloud).
   - The steps one after another on one thread, each its wall and CPU seconds: the augmented
     views for eq. (4) (``view_grids``: drawn, mapped, gridded), the rendered views (``views``:
     render, normals, their grids mapped), distance field and surface, symmetry, the refit of
     the classifier (``Engine.add``) and the self-check (``self_check_poses`` renders, and
     twice as many views of each part it may be taken for: ``Engine.registration_check``).
   - The registration as the service runs it (``make_reference``, its network thread beside
     the geometry; ``add``; the self-check, two renders at a time): wall, the CPU of every
     thread, and its critical path, the busier thread's CPU seconds plus the serial steps:
     what the wall comes to on two cores the machine's other work leaves alone.
2. Through HTTP (unless ``--skip-http``): ``python -m service`` on the shipped gallery, each
   part's mesh posted one at a time (the wall of each), then the same meshes under new names as
   one folder, ``dpc-mn register FOLDER``: one request, one refit (its wall and refits).

The load average is printed with the figures: on a shared machine walls stretch with it, CPU
seconds much less. Every count is fixed and the run stops by itself; nothing leaves loopback.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from evaluation.served import ServiceProcess
from service.api import startup
from service.client import Client
from service.engine.classifier import view_features
from service.engine.distance_field import DistanceField
from service.engine.engine import VIEW_POINTS, Engine
from service.engine.grid import grid
from service.engine.icp import Surface
from service.engine.normalize import radius
from service.engine.normals import estimate_normals, mesh_normals, orient_by_views
from service.engine.sampling import sample_surface_faces
from service.engine.symmetry import find_symmetry
from service.engine.views import directions, facing, render
from service.gallery.gallery_file import load_gallery
from service.settings import Settings
from training.objects import load_manifest, load_object_meshes

STEPS = ("view_grids", "views", "field", "symmetry", "refit", "self_check")


@contextmanager
def timed(into: dict, step: str):
    """Add the block's wall and process CPU seconds to ``into[step]``."""
    wall, cpu = time.perf_counter(), time.process_time()
    yield
    into.setdefault(step, [0.0, 0.0])
    into[step][0] += time.perf_counter() - wall
    into[step][1] += time.process_time() - cpu


def steps(engine: Engine, name: str, mesh: trimesh.Trimesh | None, points, faces) -> dict:
    """Each step of one registration, one after another on this thread."""
    settings, spent = engine.settings, {}
    points32 = np.asarray(points, np.float32)
    with timed(spent, "view_grids"):
        rng = np.random.default_rng(settings.seed)
        engine.map(points32, quiet=True)
        augmented = [engine.augmented_view(points32, rng) for _ in range(settings.view_grids)]
        for view in augmented:
            grid(engine.map(view, quiet=True))
    scale, cloud = radius(points32), points32.astype(np.float64)
    tree = cKDTree(cloud)
    with timed(spent, "views"):
        count = settings.views
        if mesh is not None:
            dense = trimesh.sample.sample_surface(
                mesh, settings.mesh_surface_points, seed=settings.seed + 1
            )[0]
            visible = render(cloud, scale, count, np.asarray(dense), mesh.area)
            normals = mesh_normals(mesh, faces, cloud, directions(count), visible)
        else:
            visible = render(cloud, scale, count, tree=tree)
            normals = orient_by_views(
                cloud, estimate_normals(cloud, tree=tree), directions(count), visible
            )
            visible &= facing(cloud, normals, scale, count)
        grids = [grid(engine.map(cloud[seen][:VIEW_POINTS], quiet=True)) for seen in visible]
        view_features(np.stack(grids), settings.grid_blur)
    with timed(spent, "field"):
        surface = Surface.of(cloud, normals, DistanceField.of(cloud, scale, tree=tree), tree)
    with timed(spent, "symmetry"):
        find_symmetry(surface, scale, np.random.default_rng(0))
    reference = engine.make_reference(name, points, mesh=mesh, face_index=faces)
    with timed(spent, "refit"):
        engine.add(reference)
    with timed(spent, "self_check"):
        engine.registration_check(reference, 3, mesh)
    engine.remove(name)
    return {step: {"wall_s": w, "cpu_s": c} for step, (w, c) in spent.items()}


def registration(engine: Engine, name: str, mesh, points, faces, poses: int) -> dict:
    """One registration as the service runs it: wall, every thread's CPU, the critical path."""
    wall, cpu, main = time.perf_counter(), time.process_time(), time.thread_time()
    reference = engine.make_reference(name, points, mesh=mesh, face_index=faces)
    make_main, make_all = time.thread_time() - main, time.process_time() - cpu
    made = time.perf_counter()
    engine.add(reference)
    added, add_cpu = time.perf_counter(), time.process_time()
    engine.registration_check(reference, poses, mesh)
    done, check_cpu = time.perf_counter(), time.process_time() - add_cpu
    engine.remove(name)
    network = make_all - make_main
    return {
        "wall_s": done - wall,
        "make_wall_s": made - wall,
        "refit_wall_s": added - made,
        "self_check_wall_s": done - added,
        "cpu_s": time.process_time() - cpu,
        "make_threads_cpu_s": [make_main, network],
        # the busier thread of make_reference, the refit, the self-check's two threads
        "critical_path_s": max(make_main, network) + (add_cpu - cpu - make_all) + check_cpu / 2,
    }


def in_process(parts: int) -> dict:
    settings = Settings()
    calibration = startup.load_calibration(settings)
    engine = Engine(startup.load_model(settings), settings.engine, calibration)
    engine.load(load_gallery(settings.model.gallery)[0])
    specs = (load_manifest(split="unseen") + load_manifest(split="seen"))[:parts]
    meshes = load_object_meshes(specs)
    engine.make_reference("warm-up", np.random.default_rng(0).normal(size=(300, 3)))
    poses = settings.gallery.self_check_poses
    report: dict = {"steps": {}, "registrations": {}}
    for name, mesh in meshes.items():
        points, faces = sample_surface_faces(mesh, settings.gallery.reference_points, 0)
        for kind, given in (("mesh", mesh), ("cloud", None)):
            index = faces if given is not None else None
            key = f"{name}/{kind}"
            report["steps"][key] = steps(engine, f"bench-{name}", given, points, index)
            report["registrations"][key] = registration(
                engine, f"bench-{name}", given, points, index, poses
            )
            print(f"  {key}: {report['registrations'][key]}", flush=True)
    return report


def summary(report: dict) -> dict:
    """Medians over the parts, by kind (mesh, cloud)."""
    out: dict = {}
    for kind in ("mesh", "cloud"):
        keys = [k for k in report["registrations"] if k.endswith(f"/{kind}")]
        steps_of = [report["steps"][k] for k in keys]
        out[kind] = {
            "steps_cpu_s": {s: statistics.median(x[s]["cpu_s"] for x in steps_of) for s in STEPS},
            "steps_wall_s": {s: statistics.median(x[s]["wall_s"] for x in steps_of) for s in STEPS},
        }
        for field in ("wall_s", "cpu_s", "critical_path_s", "make_wall_s", "self_check_wall_s"):
            values = [report["registrations"][k][field] for k in keys]
            out[kind][f"{field}_median"] = statistics.median(values)
            out[kind][f"{field}_max"] = max(values)
    return out


def over_http(parts: int, workdir: Path) -> dict:
    specs = (load_manifest(split="unseen") + load_manifest(split="seen"))[:parts]
    folder = workdir / "parts"
    folder.mkdir()
    for spec in specs:
        (folder / f"batch-{spec.name}{spec.path.suffix}").write_bytes(spec.path.read_bytes())
    walls = []
    with (
        ServiceProcess(
            workdir / "service.log",
            gallery__data_dir=str(workdir / "data"),
            server__log_level="warning",
            auth__keys="{}",
        ) as server,
        Client(server.url, retry_for=0) as client,
    ):
        for spec in specs:
            began = time.perf_counter()
            client.register(f"one-{spec.name}", spec.path)
            walls.append(time.perf_counter() - began)
        files = [("file", (p.name, p.read_bytes())) for p in sorted(folder.iterdir())]
        began = time.perf_counter()
        answered = httpx.post(f"{server.url}/references/batch", files=files, timeout=600)
        batch = time.perf_counter() - began
        answered.raise_for_status()
        answer = answered.json()
    return {
        "one_at_a_time_s": walls,
        "one_at_a_time_median_s": statistics.median(walls),
        "batch_parts": len(specs),
        "batch_wall_s": batch,
        "batch_refits": answer["refits"],
        "batch_per_part_s": batch / len(specs),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", type=int, default=6)
    parser.add_argument("--skip-http", action="store_true")
    parser.add_argument("--json", type=Path, help="write the figures here too")
    args = parser.parse_args(argv)
    report: dict = {"load_average_at_start": os.getloadavg(), "cpus": os.cpu_count()}
    print(f"in process: {args.parts} parts, as meshes and clouds ...", flush=True)
    report["in_process"] = in_process(args.parts)
    report["summary"] = summary(report["in_process"])
    if not args.skip_http:
        print("over HTTP: one at a time, then one batch ...", flush=True)
        with tempfile.TemporaryDirectory(prefix="dpc-registration-") as folder:
            report["http"] = over_http(args.parts, Path(folder))
    report["load_average_at_end"] = os.getloadavg()
    shown = {k: v for k, v in report.items() if k != "in_process"}
    print(json.dumps(shown, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
