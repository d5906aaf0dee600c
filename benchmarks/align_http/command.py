"""The command line of ``python -m benchmarks.align_http`` (the package's docstring): the
arguments, then each job in turn: clouds, padding, timing per size and provider, the growth,
the refit, the accuracy, the report."""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import onnxruntime as ort

from benchmarks.align_http.accuracy import accuracy
from benchmarks.align_http.clouds import make_clouds
from benchmarks.align_http.padding import padding_references
from benchmarks.align_http.report import BASE_REFERENCES, TARGET_GROWTH_MS, TARGET_MS, print_report
from benchmarks.align_http.timing import growth, measure, paired_growth, refit_time
from service.api.startup import load_calibration
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.gallery.gallery_file import load_gallery
from service.settings import Settings


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    settings = Settings()
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.align_http",
        description="POST /align latency and throughput over HTTP, beside the engine's time.",
    )
    parser.add_argument("--model", type=Path, default=settings.model.path, help="the ONNX model")
    parser.add_argument(
        "--gallery", type=Path, default=settings.model.gallery, help="the shipped gallery (.npz)"
    )
    parser.add_argument(
        "--references",
        type=int,
        nargs="+",
        default=[BASE_REFERENCES],
        help=f"gallery sizes to measure (a size over {BASE_REFERENCES} also measures "
        f"{BASE_REFERENCES}, the baseline of the growth figure); e.g. --references 1000",
    )
    parser.add_argument("--requests", type=int, default=200, help="sequential requests per body")
    parser.add_argument("--warmup", type=int, default=10, help="warm-up requests, not counted")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument(
        "--concurrent-requests", type=int, default=120, help="requests per concurrency level"
    )
    parser.add_argument("--clouds-per-object", type=int, default=2, help="clouds per reference")
    parser.add_argument(
        "--registrations",
        type=int,
        default=3,
        help="times one reference is removed and registered again, without and with the check",
    )
    parser.add_argument(
        "--providers",
        choices=("auto", "cpu", "cuda", "both"),
        default="auto",
        help="onnxruntime execution providers to measure (auto: both where onnxruntime offers "
        "CUDA, else the CPU)",
    )
    parser.add_argument("--refit-references", type=int, default=100)
    parser.add_argument("--refit-repeats", type=int, default=5)
    parser.add_argument(
        "--accuracy",
        action="store_true",
        help="also measure success shares on pybullet's meshes (needs the train extra)",
    )
    parser.add_argument(
        "--accuracy-poses", type=int, default=4, help="poses per object and family (accuracy)"
    )
    parser.add_argument("--accuracy-clients", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ready-timeout", type=float, default=900.0, help="seconds")
    parser.add_argument(
        "--padding-cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "dpc_bench_cache",
        help="where computed padding references are kept between runs ('' for nowhere)",
    )
    parser.add_argument(
        "--padding-workers", type=int, default=1, help="processes computing padding references"
    )
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args(argv)
    sizes = sorted(set(args.references))
    if any(s < 1 for s in sizes) or args.requests < 1 or args.concurrent_requests < 1:
        parser.error("sizes and request counts must be positive")
    if max(sizes) > BASE_REFERENCES and BASE_REFERENCES not in sizes:
        sizes.insert(0, BASE_REFERENCES)
    args.references = sizes
    if str(args.padding_cache) in ("", "."):
        args.padding_cache = None
    if not args.model.is_file():
        parser.error(f"no ONNX model at {args.model}: pass --model or set DPC_MODEL__PATH")
    if not args.gallery.is_file():
        parser.error(f"no gallery at {args.gallery}: pass --gallery or set DPC_MODEL__GALLERY")
    if args.accuracy and not installed("pybullet_data"):
        parser.error(
            "--accuracy aligns pybullet's meshes: install the train extra "
            "(pip install -e '.[train]'), or leave --accuracy out"
        )
    cuda = "CUDAExecutionProvider" in ort.get_available_providers()
    if args.providers == "auto":
        args.providers = ["cpu", "cuda"] if cuda else ["cpu"]
    else:
        args.providers = ["cpu", "cuda"] if args.providers == "both" else [args.providers]
        if "cuda" in args.providers and not cuda:
            parser.error("onnxruntime offers no CUDA execution provider here (onnxruntime-gpu)")
    return args


def installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def run(args: argparse.Namespace, progress: Callable[[str], None] = print) -> dict:
    settings = Settings()
    settings = settings.model_copy(
        update={"model": settings.model.model_copy(update={"path": args.model})}
    )
    engines = {}
    for provider in args.providers:
        mapper = Mapper(
            args.model,
            settings.model.intra_op_threads,
            settings.model.inter_op_threads,
            provider == "cuda",
            blas_threads=settings.model.blas_threads,
        )
        engines[provider] = Engine(mapper, settings.engine, load_calibration(settings))
    engine = engines[args.providers[0]]
    model_hash = engine.mapper.model_hash
    shipped, meta = load_gallery(args.gallery)
    gallery_hash = meta.get("model_sha256") or meta.get("model_hash")
    if gallery_hash != model_hash:
        progress("the gallery was computed with another model: recomputing its references")
        shipped = [engine.make_reference(r.name, r.points) for r in shipped]
    clouds = make_clouds(
        shipped[: min(BASE_REFERENCES, *args.references)], args.clouds_per_object, args.seed
    )
    needed = max(args.references) - len(shipped)
    padding, computed, padding_s = padding_references(
        engine, shipped, needed, args.padding_cache, args.padding_workers, progress
    )
    report: dict = {
        "config": {
            "model": str(args.model),
            "model_sha256": model_hash,
            "gallery": str(args.gallery),
            "providers": {p: e.mapper.providers for p, e in engines.items()},
            "onnxruntime": ort.__version__,
            "engine_settings": settings.engine.model_dump(mode="json"),
            "calibration": engine.calibration is not None,
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "clouds": len(clouds),
            "cloud_objects": len({c.label for c in clouds}),
            "requests": args.requests,
            "warmup": args.warmup,
            "concurrent_requests": args.concurrent_requests,
            "seed": args.seed,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "load_average_at_start": os.getloadavg(),  # other work on the machine skews it all
        },
        "targets": {"median_ms": TARGET_MS, "growth_ms": TARGET_GROWTH_MS},
        "padding": {
            "references": len(padding),
            "computed": computed,
            "compute_s": padding_s,
            "workers": args.padding_workers,
            "cache": None if args.padding_cache is None else str(args.padding_cache),
        },
        "runs": [],
    }
    gallery = shipped + padding
    with tempfile.TemporaryDirectory(prefix="dpc-bench-") as tmp:
        for size in args.references:
            references = gallery[:size]
            for provider in args.providers:
                report["runs"].append(
                    measure(
                        size,
                        provider,
                        args,
                        engines[provider],
                        references,
                        model_hash,
                        clouds,
                        Path(tmp),
                    )
                )
        report["growth"] = growth(report["runs"])
        for grown in report["growth"]:
            small, large = gallery[: grown["from"]], gallery[: grown["to"]]
            provider = grown["provider"]
            grown["paired"] = paired_growth(
                small, large, provider, args, engines[provider], model_hash, clouds, Path(tmp)
            )
        report["refit"] = refit_time(
            gallery, args.refit_references, args.refit_repeats, settings.engine
        )
        if args.accuracy:
            report["accuracy"] = accuracy(args, shipped, model_hash, Path(tmp))
    report["config"]["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    report["config"]["load_average_at_end"] = os.getloadavg()
    return report


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    report = run(args)
    print_report(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
