"""``dpc-mn``: the service from a shell, through ``service.client.Client``.

    dpc-mn register bracket.stl --name bracket-a
    dpc-mn register bracket-cad.stl --name bracket-b --units mm
    dpc-mn register parts/                      # every mesh in the folder: one request, one refit
    dpc-mn align scan.pcd --candidates bracket-a
    dpc-mn align depth.png --fx 300 --fy 300 --cx 160 --cy 120 --mask part.png --json
    dpc-mn detect frame.pcd --max-instances 6
    dpc-mn references
    dpc-mn backup gallery.sqlite3               # a consistent copy while the service serves
    dpc-mn restore gallery.sqlite3              # into an empty gallery, every row checked
    dpc-mn export cell-4.sqlite3 --names bracket-a,bracket-b
    dpc-mn import cell-4.sqlite3 --url http://new-line:8000
    dpc-mn serve --port 9000

Every command takes ``--url`` (``DPCMN_URL``), ``--api-key`` (``DPCMN_API_KEY``), ``--json``
(the service's answer as JSON on stdout, for scripts; errors too) and ``--retry-for`` (seconds
within which a call is sent again after a connection error, a 502 or a 503; every command's
call is safe to send again). Exit status: see ``EPILOG``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from service.client.answers import Pose, Reference, Scene
from service.client.client import DEFAULT_URL, Client, DepthCamera
from service.client.errors import ServiceError, Unreachable

OK, FAILED, USAGE, NOT_A_MATCH, UNREACHABLE = 0, 1, 2, 3, 4
EPILOG = """exit status:
  0  done (align: the verdict is "match", safe to act on; detect: at least one "match")
  1  the service refused or failed the request (the reason is printed)
  2  a bad command line
  3  align answered, but the verdict is "uncertain" or "no_match"; detect found no "match"
  4  the service could not be reached"""
URL_ENV, KEY_ENV = "DPCMN_URL", "DPCMN_API_KEY"
PART_SUFFIXES = (".stl", ".obj", ".ply", ".pcd", ".npy", ".off", ".glb", ".gltf")
UNITS = ("m", "mm", "cm", "in")  # POST /references' units


def json_object(text: str) -> dict:
    """A command-line argument holding a JSON object (argparse names the option on error)."""
    try:
        value = json.loads(text)
    except ValueError:
        value = None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"not a JSON object: {text[:80]!r}")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    arguments = parser().parse_args(argv)
    if arguments.command == "serve":
        serve(arguments)  # does not return
    try:
        with Client(
            arguments.url,
            arguments.api_key,
            arguments.timeout,
            retry_for=arguments.retry_for,
            on_retry=say_retry,
        ) as client:
            return arguments.run(client, arguments)
    except ServiceError as error:
        return report_error(in_cli_words(error), arguments.json)
    except OSError as error:  # a file that cannot be read
        return report_error(ServiceError(f"{error.strerror}: {error.filename}"), arguments.json)


def observation_arguments(sub: argparse.ArgumentParser) -> None:
    """What align and detect both take: candidates, viewpoint, confidence, a depth camera."""
    sub.add_argument("--candidates", type=names, help="reference names, comma-separated")
    sub.add_argument(
        "--viewpoint", type=vector, help="where the sensor was: x,y,z (--viewpoint=-1,0,0)"
    )
    sub.add_argument("--min-confidence", type=float, help="below it, never 'match' (0 to 1)")
    for name in ("fx", "fy", "cx", "cy"):
        sub.add_argument(f"--{name}", type=float, help="depth image: camera intrinsic, pixels")
    sub.add_argument("--depth-scale", type=float, help="depth image: scene units per value")
    sub.add_argument("--mask", help="depth image: an image of the same size; 0 leaves out")
    sub.add_argument("--topic", help="ROS bag: the PointCloud2 topic (default: its only one)")
    sub.add_argument(
        "--message", type=int, default=0, help="ROS bag: which message, 0 the first, -1 the last"
    )


def parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--url",
        default=os.environ.get(URL_ENV, DEFAULT_URL),
        help=f"the service (${URL_ENV}; default {DEFAULT_URL})",
    )
    common.add_argument(
        "--api-key",
        default=os.environ.get(KEY_ENV),
        help=f"an API key, sent as 'Authorization: Bearer' (${KEY_ENV})",
    )
    common.add_argument("--timeout", type=float, default=60.0, help="seconds (default 60)")
    common.add_argument(
        "--retry-for",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="send a call again after a connection error, 502 or 503 within this time "
        "(default 30; 0: never)",
    )
    common.add_argument("--json", action="store_true", help="print the answer as JSON")
    formatter = argparse.RawDescriptionHelpFormatter
    top = argparse.ArgumentParser(
        prog="dpc-mn",
        description="Register parts with the DPC-MN pose service, align clouds and depth "
        "images against them, and start the service.",
        epilog=EPILOG,
        formatter_class=formatter,
    )
    commands = top.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, run: Callable[..., int] | None, summary: str) -> argparse.ArgumentParser:
        sub = commands.add_parser(
            name,
            parents=[] if run is None else [common],
            help=summary,
            description=summary,
            epilog=EPILOG,
            formatter_class=formatter,
        )
        sub.set_defaults(run=run)
        return sub

    align = command("align", run_align, "Recognise the part in a cloud file and estimate its pose")
    align.add_argument(
        "file",
        help="a cloud (.ply, .pcd, .npy), a depth image (.png, .tif, .npy) with --fx..., or a "
        "ROS bag (.bag, .db3, .mcap, a ROS 2 bag's folder) with --topic",
    )
    observation_arguments(align)
    align.add_argument("--top-k", type=int, help="candidates to verify geometrically")
    align.add_argument(
        "--no-refine", dest="refine", action="store_false", default=None, help="skip ICP"
    )

    detect = command("detect", run_detect, "Find every registered part in a camera's whole frame")
    detect.add_argument(
        "file",
        help="an organized cloud (.pcd, .npy), a cloud, a depth image with --fx..., or a ROS "
        "bag (.bag, .db3, .mcap, a ROS 2 bag's folder) with --topic",
    )
    observation_arguments(detect)
    detect.add_argument("--max-instances", type=int, help="at most this many detections")
    detect.add_argument(
        "--roi", type=box, help="the box searched: min_x,min_y,min_z,max_x,max_y,max_z"
    )

    register = command(
        "register", run_register, "Register a part from a mesh or cloud file, or a folder of them"
    )
    register.add_argument(
        "file",
        help="a mesh (.stl, .obj, .ply) or a cloud (.ply, .pcd, .npy), or a folder of them: "
        "every part in one request (all or none), each named for its file",
    )
    register.add_argument(
        "--name", help="1-64 characters of A-Z a-z 0-9 . _ - (default: the file's name)"
    )
    register.add_argument("--replace", action="store_true", help="replace a part of that name")
    register.add_argument(
        "--units",
        choices=UNITS,
        help="the unit the file's points are in (stored in metres; default: as they are)",
    )
    register.add_argument(
        "--symmetry",
        type=json_object,
        help="a symmetry you declare, as JSON in the file's own frame, e.g. "
        '\'{"kind": "discrete", "axis": [0, 0, 1], "order": 2}\' or '
        '\'{"kind": "revolution", "axis": [0, 0, 1]}\' (one part only)',
    )
    register.add_argument(
        "--no-self-check", dest="self_check", action="store_false", help="skip the self-check"
    )

    command("references", run_references, "List the registered parts")
    delete = command("delete", run_delete, "Remove a registered part")
    delete.add_argument("name")
    command("health", run_health, "The service's status, model and number of references")
    backup = command("backup", run_backup, "A consistent copy of the gallery, while it serves")
    backup.add_argument("file", help="where to write the copy (an SQLite file)")
    restore = command("restore", run_restore, "Restore a backup into an empty gallery")
    restore.add_argument("file", help="a copy written by dpc-mn backup")
    restore.add_argument(
        "--replace", action="store_true", help="replace every reference the gallery holds"
    )
    export = command("export", run_export, "Copy chosen references, for another service")
    export.add_argument("file", help="where to write the copy (an SQLite file)")
    export.add_argument("--names", type=names, required=True, help="comma-separated")
    imported = command("import", run_import, "Add the references of an export")
    imported.add_argument("file", help="a copy written by dpc-mn export (or backup)")
    imported.add_argument(
        "--replace", action="store_true", help="replace references of those names"
    )

    serve_command = command("serve", None, "Start the service (as python -m service)")
    serve_command.add_argument("--host", help="address to listen on (DPC_SERVER__HOST)")
    serve_command.add_argument("--port", type=int, help="port to listen on (DPC_SERVER__PORT)")
    return top


def depth_camera(arguments: argparse.Namespace) -> DepthCamera | None:
    """The depth image's camera from ``--fx --fy --cx --cy --depth-scale``; None without."""
    intrinsics = [arguments.fx, arguments.fy, arguments.cx, arguments.cy]
    if any(value is not None for value in intrinsics) or arguments.depth_scale is not None:
        return DepthCamera(*intrinsics, depth_scale=arguments.depth_scale)  # type: ignore[arg-type]
    return None


def run_align(client: Client, arguments: argparse.Namespace) -> int:
    camera = depth_camera(arguments)
    pose = client.align_file(
        arguments.file,
        arguments.viewpoint,
        arguments.candidates,
        camera=camera,
        mask=arguments.mask,
        top_k=arguments.top_k,
        refine=arguments.refine,
        min_confidence=arguments.min_confidence,
        topic=arguments.topic,
        message=arguments.message,
    )
    print(json.dumps(pose.raw) if arguments.json else describe_pose(pose))
    return OK if pose.is_match else NOT_A_MATCH


def run_detect(client: Client, arguments: argparse.Namespace) -> int:
    scene = client.detect(
        arguments.file,
        arguments.viewpoint,
        arguments.candidates,
        camera=depth_camera(arguments),
        mask=arguments.mask,
        max_instances=arguments.max_instances,
        min_confidence=arguments.min_confidence,
        roi=arguments.roi,
        topic=arguments.topic,
        message=arguments.message,
    )
    print(json.dumps(scene.raw) if arguments.json else describe_scene(scene))
    return OK if scene.matches else NOT_A_MATCH


def run_register(client: Client, arguments: argparse.Namespace) -> int:
    source = Path(arguments.file)
    if source.is_dir():
        if arguments.name:
            raise ServiceError("--name names one part: leave it out to register a folder")
        if arguments.symmetry:
            raise ServiceError("--symmetry declares one part's: register that part alone")
        parts = sorted(p for p in source.iterdir() if p.suffix.lower() in PART_SUFFIXES)
        if not parts:
            raise ServiceError(f"no mesh or cloud file ({', '.join(PART_SUFFIXES)}) in {source}")
        references = client.register_many(
            parts,
            replace=arguments.replace,
            self_check=arguments.self_check,
            units=arguments.units,
        )
    else:
        name = arguments.name or source.stem
        references = [
            client.register(
                name,
                source,
                replace=arguments.replace,
                self_check=arguments.self_check,
                units=arguments.units,
                symmetry=arguments.symmetry,
            )
        ]
    if arguments.json:
        raw = [r.raw for r in references]
        print(json.dumps(raw[0] if not source.is_dir() else {"references": raw}))
    else:
        print("\n".join(describe_reference(reference) for reference in references))
    return OK


def run_backup(client: Client, arguments: argparse.Namespace) -> int:
    count = client.backup(arguments.file)
    said = {"file": arguments.file, "references": count}
    print(json.dumps(said) if arguments.json else f"{count} references copied to {arguments.file}")
    return OK


def run_export(client: Client, arguments: argparse.Namespace) -> int:
    count = client.export(arguments.file, arguments.names)
    said = {"file": arguments.file, "references": count}
    print(json.dumps(said) if arguments.json else f"{count} references copied to {arguments.file}")
    return OK


def run_restore(client: Client, arguments: argparse.Namespace) -> int:
    answer = client.restore(arguments.file, replace=arguments.replace)
    if arguments.json:
        print(json.dumps(answer))
    elif answer["outcome"] == "identical":
        print(f"the gallery holds the copy's {answer['restored']} references already")
    else:
        print(
            f"restored {answer['restored']} references from {arguments.file}; every row's "
            f"checksum and points_sha256 checked ({answer['checked']})"
        )
    return OK


def run_import(client: Client, arguments: argparse.Namespace) -> int:
    references = client.import_references(arguments.file, replace=arguments.replace)
    if arguments.json:
        print(json.dumps({"references": [r.raw for r in references]}))
    else:
        for reference in references:
            print(f"{reference.raw.get('outcome', 'imported')}: {reference.name}")
    return OK


def run_references(client: Client, arguments: argparse.Namespace) -> int:
    references = client.references()
    if arguments.json:
        print(json.dumps({"references": [r.raw for r in references]}))
    else:
        print(f"{len(references)} references")
        for r in references:
            print(f"  {r.name:<32} {r.num_points:>7} points  scale {r.scale:.4g}")
    return OK


def run_delete(client: Client, arguments: argparse.Namespace) -> int:
    client.delete(arguments.name)
    print(
        json.dumps({"deleted": arguments.name}) if arguments.json else f"deleted {arguments.name}"
    )
    return OK


def run_health(client: Client, arguments: argparse.Namespace) -> int:
    health = client.health()
    if arguments.json:
        print(json.dumps(health))
    else:
        print(
            f"{health['status']}: {health['references']} references, auth {health['auth']}, "
            f"providers {', '.join(health['providers'])}"
        )
    return OK if health["status"] == "ok" else FAILED


def serve(arguments: argparse.Namespace) -> None:
    """Become ``python -m service`` with the same flags (its signals, its exit status)."""
    flags = [
        f"--{name}={value}" for name in ("host", "port") if (value := getattr(arguments, name))
    ]
    os.execv(sys.executable, [sys.executable, "-m", "service", *flags])


def describe_pose(pose: Pose) -> str:
    confidence = "unknown" if pose.confidence is None else f"{pose.confidence:.2f}"
    lines = [
        f"{pose.verdict}: {pose.label} (confidence {confidence}, score {pose.score:.3f})",
        f"  alignment error {pose.alignment_error:.4g} "
        f"({pose.alignment_error_normalized:.3f} of the scale), hypothesis {pose.hypothesis}",
        f"  rotation    {_rows(pose.rotation)}",
        f"  translation {_row(pose.translation)}",
    ]
    lines += [f"  reason: {reason}" for reason in pose.reasons]
    if pose.ambiguous:
        parts = sorted({a.label for a in pose.alternatives if a.label})
        poses = sum(a.label is None for a in pose.alternatives)
        said = [f"{poses} other pose(s)"] if poses else []
        said += [f"look-alike part(s) {', '.join(parts)}"] if parts else []
        lines.append(f"  ambiguous: {' and '.join(said) or 'other poses'} fit alike")
    if pose.points_set_aside:
        lines.append(f"  {pose.points_set_aside} points set aside (support plane, strays)")
    timings = ", ".join(f"{k} {v:.1f}" for k, v in pose.timings_ms.items())
    lines.append(f"  timings (ms): {timings}")
    return "\n".join(lines)


def describe_scene(scene: Scene) -> str:
    lines = [
        f"{len(scene.matches)} of {len(scene.detections)} detection(s) match, in "
        f"{scene.num_points} points ({scene.unexplained} unexplained)"
    ]
    for detection in scene.detections:
        confidence = "unknown" if detection.confidence is None else f"{detection.confidence:.2f}"
        lines += [
            f"{detection.verdict}: {detection.label} (confidence {confidence}, "
            f"{len(detection.indices)} points)",
            f"  rotation    {_rows(detection.rotation)}",
            f"  translation {_row(detection.translation)}",
        ]
        lines += [f"  reason: {reason}" for reason in detection.reasons]
    if not scene.complete:
        lines += [f"incomplete: {reason}" for reason in scene.reasons]
    timings = ", ".join(f"{k} {v:.1f}" for k, v in scene.timings_ms.items())
    lines.append(f"timings (ms): {timings}")
    return "\n".join(lines)


def describe_reference(reference: Reference) -> str:
    done = f"registered {reference.name}"
    if reference.raw.get("outcome") == "identical":
        done = f"{reference.name} was already registered, identical"
    text = f"{done}: {reference.num_points} points, scale {reference.scale:.4g}"
    checks = reference.self_check or []
    if checks:
        right = sum(bool(check.get("label_ok")) for check in checks)
        worst = max(float(check.get("rotation_error_deg", 0.0)) for check in checks)
        text += f"\n  self-check: {right}/{len(checks)} recognised, worst rotation {worst:.1f} deg"
    if reference.symmetry:
        text += f"\n  symmetry: {reference.symmetry.get('kind')}"
    warnings = (f"  warning: {as_flags(warning)}" for warning in reference.warnings)
    return "\n".join([text, *warnings])


def in_cli_words(error: ServiceError) -> ServiceError:
    """The error with the service's names for a registration's options said as this command
    line's flags (``as_flags``)."""
    detail = as_flags(error.detail)
    if detail == error.detail:
        return error
    return type(error)(detail, error.status, error.request_id, error.retry_after)


def as_flags(text: str) -> str:
    """The service's words for a registration's query parameters as ``dpc-mn``'s flags: it says
    "pass replace=true" and "units=mm", the command line takes ``--replace`` and ``--units mm``
    (and, once a taken name is said, ``--name``)."""
    if re.search(r"\bpass \??replace=true\b", text):
        text = text.replace("pick another name", "pick another --name")
    text = re.sub(r"\??\breplace=true\b", "--replace", text)
    return re.sub(r"\??\bunits=(m|mm|cm|in)\b", r"--units \1", text)


def say_retry(error: ServiceError, wait_s: float) -> None:
    print(f"dpc-mn: {error}; sending it again in {wait_s:.1f} s", file=sys.stderr)


def report_error(error: ServiceError, as_json: bool) -> int:
    if as_json:
        print(json.dumps({"error": {"status": error.status, "detail": error.detail}}))
    print(f"dpc-mn: {error}", file=sys.stderr)
    return UNREACHABLE if isinstance(error, Unreachable) else FAILED


def names(text: str) -> list[str]:
    return [name.strip() for name in text.split(",") if name.strip()]


def numbers(text: str, count: int, names: str) -> list[float]:
    """``count`` comma-separated numbers, or argparse's error naming their layout."""
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count:
        said = {3: "three", 6: "six"}.get(count, str(count))
        raise argparse.ArgumentTypeError(f"'{text}' is not {said} numbers {names}")
    return values


def vector(text: str) -> list[float]:
    return numbers(text, 3, "x,y,z")


def box(text: str) -> tuple[list[float], list[float]]:
    values = numbers(text, 6, "min_x,min_y,min_z,max_x,max_y,max_z")
    return values[:3], values[3:]


def _row(values: Any) -> str:
    return "[" + ", ".join(f"{v: .6f}" for v in values) + "]"


def _rows(matrix: Any) -> str:
    return "[" + ", ".join(_row(row) for row in matrix) + "]"


if __name__ == "__main__":
    sys.exit(main())
