"""Export a trained network to ONNX and build the gallery the service ships with.

    python -m training.export --checkpoint runs/shipped/checkpoint.pt --out models
    python -m training.export --checkpoint runs/x/checkpoint.pt --out runs/x/export --onnx-only

Writes ``dpc_mn.onnx`` (dynamic number of points, opset 17, its input convention
in the metadata), checks it against PyTorch with onnxruntime on clouds of
several sizes, builds ``gallery.npz`` from the seen objects (each reference is the
mesh sampled with seed 0, mapped by the exported model through the service's own
engine, with the grids of augmented views its classifier is fitted on), and
writes ``manifest.json``: file hashes, training config, date and code version.
``--onnx-only`` writes and checks ``dpc_mn.onnx`` alone (no gallery, no manifest): enough for
a study that registers its own references (``evaluation.views_mapping``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from tqdm import tqdm

from service.engine.engine import Engine
from service.engine.mapping import INPUT_NAME, OUTPUT_NAME, Mapper, file_sha256
from service.engine.sampling import sample_surface_faces
from service.gallery.gallery_file import save_gallery
from service.settings import EngineSettings, GallerySettings
from training.model import DPCMN
from training.objects import load_manifest, load_object_meshes
from training.train import config_from_dict

OPSET = 17
PARITY_SIZES = (64, 500, 1024, 2048, 5000)
PARITY_TOLERANCE = 1e-4


def load_checkpoint(path: Path):
    checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    config = config_from_dict(checkpoint["config"])
    model = DPCMN(config.model)
    model.load_state_dict(checkpoint["model"])
    return model.eval(), config, checkpoint


def export_onnx(model: DPCMN, canonical: bool, path: Path, extra: dict) -> None:
    example = torch.randn(1, 1024, 3)
    torch.onnx.export(
        model,
        (example,),
        str(path),
        input_names=[INPUT_NAME],
        output_names=[OUTPUT_NAME],
        dynamic_axes={
            INPUT_NAME: {0: "batch", 1: "points"},
            OUTPUT_NAME: {0: "batch", 1: "points"},
        },
        opset_version=OPSET,
        dynamo=False,
    )
    graph = onnx.load(str(path))
    metadata = {"canonical": "true" if canonical else "false", **extra}
    for key, value in metadata.items():
        graph.metadata_props.append(onnx.StringStringEntryProto(key=key, value=value))
    onnx.checker.check_model(graph)
    onnx.save(graph, str(path))


def check_parity(model: DPCMN, path: Path) -> float:
    """The largest |onnxruntime - PyTorch| over random clouds of several sizes; raises past 1e-4."""
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    worst = 0.0
    for size in PARITY_SIZES:
        cloud = rng.uniform(-1, 1, (1, size, 3)).astype(np.float32)
        with torch.no_grad():
            expected = model(torch.from_numpy(cloud)).numpy()
        actual = session.run([OUTPUT_NAME], {INPUT_NAME: cloud})[0]
        worst = max(worst, float(np.abs(actual - expected).max()))
    if worst > PARITY_TOLERANCE:
        raise RuntimeError(
            f"ONNX export disagrees with PyTorch by {worst:.2e} > {PARITY_TOLERANCE}"
        )
    return worst


def code_version() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def build_gallery(mapper: Mapper, specs, engine_settings: EngineSettings, points: int):
    """One reference per object: its mesh sampled with seed 0, prepared by the engine as a
    mesh upload is (views rendered on the mesh, normals of its faces)."""
    engine = Engine(mapper, engine_settings)
    meshes = load_object_meshes(specs)
    references = []
    for spec in tqdm(specs, desc="gallery", leave=False):
        sampled, faces = sample_surface_faces(meshes[spec.name], points, 0)
        references.append(
            engine.make_reference(spec.name, sampled, mesh=meshes[spec.name], face_index=faces)
        )
    return references


def write_gallery(out: Path, mapper: Mapper, manifest_objects: Path | None, split: str) -> dict:
    """Build and write ``gallery.npz``; returns the manifest's entry for it."""
    specs = load_manifest(manifest_objects, split=split)
    engine_settings, gallery_settings = EngineSettings(), GallerySettings()
    references = build_gallery(mapper, specs, engine_settings, gallery_settings.reference_points)
    gallery_meta = {
        "model_sha256": mapper.model_hash,
        "reference_points": gallery_settings.reference_points,
        "reference_seed": 0,
        "view_grids": engine_settings.view_grids,
        "views": engine_settings.views,
        "split": split,
    }
    path = out / "gallery.npz"
    save_gallery(path, references, gallery_meta)
    print(f"gallery {path}: {len(references)} references")
    return gallery_meta | {"references": [r.name for r in references]}


def files_entry(*paths: Path) -> dict:
    return {p.name: {"sha256": file_sha256(p), "bytes": p.stat().st_size} for p in paths}


def gallery_only(out: Path, manifest_objects: Path | None, split: str) -> None:
    """Rebuild ``gallery.npz`` for the model already in ``out`` (after the engine's reference
    changed) and update its entries in ``manifest.json``; the model and its record stay."""
    began = time.perf_counter()
    onnx_path = out / "dpc_mn.onnx"
    manifest_path = out / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    mapper = Mapper(onnx_path, use_cuda=False)
    if manifest["files"][onnx_path.name]["sha256"] != mapper.model_hash:
        raise SystemExit(f"{onnx_path} does not match {manifest_path}: export the model again")
    manifest["gallery"] = write_gallery(out, mapper, manifest_objects, split)
    manifest["files"].update(files_entry(out / "gallery.npz"))
    manifest["gallery_code_version"] = code_version()
    manifest["gallery_seconds"] = round(time.perf_counter() - began, 1)
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"manifest {manifest_path}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=Path, default=Path("runs/shipped/checkpoint.pt"))
    parser.add_argument("--out", type=Path, default=Path("models"))
    parser.add_argument("--manifest", type=Path, default=None, help="objects (default: ours)")
    parser.add_argument("--split", default="seen", help="which objects form the gallery")
    parser.add_argument(
        "--gallery-only",
        action="store_true",
        help="rebuild gallery.npz for the model already in --out (no checkpoint needed)",
    )
    parser.add_argument(
        "--onnx-only",
        action="store_true",
        help="write and check dpc_mn.onnx alone: no gallery, no manifest",
    )
    args = parser.parse_args(argv)
    if args.gallery_only:
        gallery_only(args.out, args.manifest, args.split)
        return

    began = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    model, config, checkpoint = load_checkpoint(args.checkpoint)
    onnx_path = args.out / "dpc_mn.onnx"
    export_onnx(
        model, config.data.canonical, onnx_path, {"model": json.dumps(checkpoint["config"])}
    )
    parity = check_parity(model, onnx_path)
    print(f"ONNX export {onnx_path}: matches PyTorch within {parity:.2e}")
    if args.onnx_only:
        return

    mapper = Mapper(onnx_path, use_cuda=False)
    gallery = write_gallery(args.out, mapper, args.manifest, args.split)
    manifest = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "code_version": code_version(),
        "files": files_entry(onnx_path, args.out / "gallery.npz"),
        "onnx": {"opset": OPSET, "parity_max_abs_error": parity, "sizes": list(PARITY_SIZES)},
        "input": {"canonical": config.data.canonical, "centred": True, "scaled_by": "radius"},
        "training": checkpoint["config"],
        "trained_epochs": checkpoint["epoch"] + 1,
        "objects": checkpoint.get("objects", []),
        "gallery": gallery,
        "export_seconds": round(time.perf_counter() - began, 1),
    }
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"manifest {args.out / 'manifest.json'}")


if __name__ == "__main__":
    main()
