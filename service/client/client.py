"""``Client``: the service's HTTP API from Python, over httpx.

Points go as raw little-endian float32 (12 bytes a point), so the service aligns exactly the
float32 values of the array given; a file goes as the multipart ``file`` field and is read by
the service (PLY, PCD, NPY, STL, OBJ, and depth images with their camera). Every error answer
raises the ``service.client.errors`` type of its status, carrying the service's ``detail``.
Calls that are safe to send again (all but ``health``) are retried on a connection error, a
502 or a 503, within ``retry.total_s`` (``service.client.retry``).
"""

from __future__ import annotations

import io
import json
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from service.client.answers import Pose, Reference, Scene
from service.client.errors import ServiceError, Unreachable, error_for
from service.client.retry import RETRY_STATUSES, Retry
from service.client.rosbag import is_bag, read_bag_frame

RAW = "application/octet-stream"
COPY_TYPE = RAW  # a gallery's copy (an SQLite file), sent as its bytes
DEFAULT_URL = "http://127.0.0.1:8000"
PointsOrPath = np.ndarray | Sequence[Sequence[float]] | str | Path


@dataclass(frozen=True)
class DepthCamera:
    """A depth image's camera: pinhole intrinsics in pixels; ``depth_scale`` is scene units per
    depth value (default: 0.001 for a 16-bit image in millimetres, 1 for a float one)."""

    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float | None = None


class Client:
    """One service: ``Client(url, api_key=...)``; use it in a ``with`` block, or ``close()``.

    ``retry_for``: seconds within which a failed idempotent call is sent again (0: never);
    ``on_retry(error, wait_s)`` is told of each retry (the CLI prints it)."""

    def __init__(
        self,
        url: str = DEFAULT_URL,
        api_key: str | None = None,
        timeout: float = 60.0,
        transport: httpx.BaseTransport | None = None,
        retry_for: float = Retry.total_s,
        on_retry: Callable[[ServiceError, float], None] | None = None,
    ):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.retry = Retry(total_s=retry_for)
        self.on_retry = on_retry
        self.url = url.rstrip("/")
        self._http = httpx.Client(
            base_url=self.url, headers=headers, timeout=timeout, transport=transport
        )

    def align(
        self,
        points: np.ndarray | Sequence[Sequence[float]],
        viewpoint: Sequence[float] | None = None,
        candidates: Iterable[str] | None = None,
        *,
        top_k: int | None = None,
        refine: bool | None = None,
        min_confidence: float | None = None,
    ) -> Pose:
        """Recognise the part in ``points`` (N, 3) and estimate its pose."""
        options = _options(viewpoint, candidates, top_k, refine, min_confidence)
        return Pose.from_answer(self._post_points("/align", points, options).json())

    def align_file(
        self,
        path: str | Path,
        viewpoint: Sequence[float] | None = None,
        candidates: Iterable[str] | None = None,
        *,
        camera: DepthCamera | None = None,
        mask: str | Path | None = None,
        top_k: int | None = None,
        refine: bool | None = None,
        min_confidence: float | None = None,
        topic: str | None = None,
        message: int = 0,
    ) -> Pose:
        """Align a file as a camera tool saved it: a cloud (PLY, PCD, NPY) or a depth image
        (PNG, TIFF, NPY) with its ``camera`` (its viewpoint is then the camera, the origin);
        or a ROS bag's PointCloud2 message ``message`` of ``topic`` (``service.client.rosbag``)."""
        options = _options(viewpoint, candidates, top_k, refine, min_confidence)
        answer = self._upload("/align", path, camera, mask, options, topic, message)
        return Pose.from_answer(answer.json())

    def detect(
        self,
        frame: np.ndarray | Sequence[Sequence[float]] | str | Path,
        viewpoint: Sequence[float] | None = None,
        candidates: Iterable[str] | None = None,
        *,
        camera: DepthCamera | None = None,
        mask: str | Path | None = None,
        max_instances: int | None = None,
        min_confidence: float | None = None,
        roi: tuple[Sequence[float], Sequence[float]] | None = None,
        topic: str | None = None,
        message: int = 0,
    ) -> Scene:
        """Every registered part in a camera's whole frame: points (N, 3), or a file as
        ``align_file`` takes it (an organized PCD or NPY, a depth image with its ``camera``, a
        ROS bag's PointCloud2 message ``message`` of ``topic``). ``roi``: the (min, max)
        corners of the box searched."""
        options = _options(viewpoint, candidates, None, None, min_confidence)
        if max_instances is not None:
            options["max_instances"] = int(max_instances)
        if roi is not None:
            options["roi"] = ",".join(repr(float(v)) for corner in roi for v in corner)
        if isinstance(frame, str | Path):
            answer = self._upload("/detect", frame, camera, mask, options, topic, message)
        else:
            answer = self._post_points("/detect", frame, options)
        return Scene.from_answer(answer.json())

    def read_points(
        self, path: str | Path, camera: DepthCamera | None = None, mask: str | Path | None = None
    ) -> tuple[np.ndarray, list[float] | None]:
        """The points the service reads from a file (as ``align_file`` would align them), and
        the viewpoint the file implies (a depth image: ``[0, 0, 0]``; else None)."""
        answer = self._upload("/points", path, camera, mask, {})
        implied = answer.headers.get("X-Viewpoint")
        viewpoint = None if implied is None else [float(v) for v in implied.split(",")]
        return points_from_bytes(answer.content), viewpoint

    def register(
        self,
        name: str,
        path_or_points: PointsOrPath,
        *,
        replace: bool = False,
        self_check: bool = True,
        units: str | None = None,
        symmetry: dict | None = None,
    ) -> Reference:
        """Register a part from a mesh or cloud file, or from points (sent as float32 NPY);
        ``units`` (``m``, ``mm``, ``cm``, ``in``): the unit they are in, stored in metres;
        ``symmetry``: one the operator declares, in the points' frame (e.g. ``{"kind":
        "discrete", "axis": [0, 0, 1], "order": 2}``)."""
        if isinstance(path_or_points, str | Path):
            path = Path(path_or_points)
            file = (path.name, path.read_bytes())
        else:
            file = ("points.npy", npy_bytes(path_or_points))
        answer = self._request(
            "POST",
            "/references",
            data={"name": name}
            | ({"units": units} if units else {})
            | ({"symmetry": json.dumps(symmetry)} if symmetry else {}),
            files={"file": file},
            params={"replace": _flag(replace), "self_check": _flag(self_check)},
        )
        return Reference.from_answer(answer.json())

    def register_many(
        self,
        parts: Iterable[str | Path] | dict[str, PointsOrPath],
        *,
        replace: bool = False,
        self_check: bool = True,
        units: str | None = None,
    ) -> list[Reference]:
        """Register several parts in one request, all or none, with one refit of the
        classifier: mesh or cloud files (each named for its file, without the suffix), or
        ``{name: file or points}``, all in ``units`` (as ``register``). The answers come in
        the order given."""
        named = parts if isinstance(parts, dict) else {Path(p).stem: p for p in parts}
        files, names = [], []
        for name, source in named.items():
            if isinstance(source, str | Path):
                files.append(("file", (Path(source).name, Path(source).read_bytes())))
            else:
                files.append(("file", (f"{name}.npy", npy_bytes(source))))
            names.append(name)
        answer = self._request(
            "POST",
            "/references/batch",
            data={"name": names},
            files=files,
            params={"replace": _flag(replace), "self_check": _flag(self_check)}
            | ({"units": units} if units else {}),
        )
        return [Reference.from_answer(item) for item in answer.json()["references"]]

    def backup(self, path: str | Path) -> int:
        """A consistent copy of the whole gallery, taken while it serves, into the file
        ``path`` (written beside it, then renamed); how many references it holds."""
        return self._download("/gallery/backup", {}, Path(path))

    def export(self, path: str | Path, names: Iterable[str]) -> int:
        """A copy of the references ``names`` into ``path``, for ``import_references`` into
        another service; how many it holds."""
        return self._download("/gallery/export", {"name": list(names)}, Path(path))

    def restore(self, path: str | Path, *, replace: bool = False) -> dict[str, Any]:
        """Put a backup into a gallery that holds no reference (``replace``: in place of all
        it holds); every row and ``points_sha256`` is checked before anything is stored."""
        return self._request(
            "POST",
            "/gallery/restore",
            content=Path(path).read_bytes(),
            params={"replace": _flag(replace)},
            headers={"Content-Type": COPY_TYPE},
        ).json()

    def import_references(self, path: str | Path, *, replace: bool = False) -> list[Reference]:
        """Add the references of another service's export (``export``), all or none."""
        answer = self._request(
            "POST",
            "/gallery/import",
            content=Path(path).read_bytes(),
            params={"replace": _flag(replace)},
            headers={"Content-Type": COPY_TYPE},
        )
        return [Reference.from_answer(item) for item in answer.json()["references"]]

    def references(self) -> list[Reference]:
        answer = self._request("GET", "/references").json()
        return [Reference.from_answer(item) for item in answer["references"]]

    def reference(self, name: str) -> Reference:
        return Reference.from_answer(self._request("GET", f"/references/{name}").json())

    def reference_points(self, name: str) -> np.ndarray:
        """The points a reference was registered with (float32, model frame)."""
        return points_from_bytes(self._request("GET", f"/references/{name}/points").content)

    def delete(self, name: str) -> None:
        """Remove a reference; a retry answered 404 after an attempt that may have reached the
        service (a 502, a dropped connection) counts as removed."""
        self._request("DELETE", f"/references/{name}", gone_is_done=True)

    def health(self) -> dict[str, Any]:
        """``/health``: status, model, execution providers, references (a 503 while loading
        is answered, not raised)."""
        answer = self._send("GET", "/health")
        if answer.status_code not in (200, 503):
            raise _error(answer)
        return answer.json()

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _upload(
        self,
        route: str,
        path: str | Path,
        camera: DepthCamera | None,
        mask: str | Path | None,
        options: dict[str, Any],
        topic: str | None = None,
        message: int = 0,
    ) -> httpx.Response:
        path = Path(path)
        if is_bag(path):  # its frame as an organized NPY: the service keeps the pixel grid
            frame = read_bag_frame(path, topic, message)
            buffer = io.BytesIO()
            np.save(buffer, frame.points.astype("<f4"))
            files = {"file": (f"{path.stem}.npy", buffer.getvalue())}
        else:
            files = {"file": (path.name, path.read_bytes())}
        if mask is not None:
            files["mask"] = (Path(mask).name, Path(mask).read_bytes())
        fields = {k: v for k, v in asdict(camera).items() if v is not None} if camera else {}
        return self._request("POST", route, data=fields | options, files=files)

    def _post_points(self, route: str, points, options: dict[str, Any]) -> httpx.Response:
        """Points as raw float32 triples, the options as query parameters."""
        return self._request(
            "POST",
            route,
            content=float32_bytes(points),
            params=options,
            headers={"Content-Type": RAW},
        )

    def _download(self, route: str, params: dict[str, Any], path: Path) -> int:
        """A copy streamed into ``path`` (beside it first, renamed once whole)."""
        partial = path.with_name(path.name + ".partial")
        try:
            answer = self._request("GET", route, params=params, into=partial)
            os.replace(partial, path)
        finally:
            partial.unlink(missing_ok=True)
        return int(answer.headers.get("X-References", "0"))

    def _request(
        self, method: str, route: str, gone_is_done: bool = False, **kwargs: Any
    ) -> httpx.Response:
        """The answer of a call sent again while it fails for a reason worth a retry."""
        waits = self.retry.waits()
        reached = False  # whether an attempt so far may have reached the service
        while True:
            try:
                answer = self._send(method, route, **kwargs)
            except Unreachable as error:
                problem = error
                reached |= not isinstance(error.__cause__, httpx.ConnectError)
            else:
                if gone_is_done and reached and answer.status_code == 404:
                    return answer
                if not answer.is_error:
                    return answer
                problem = _error(answer)
                if answer.status_code not in RETRY_STATUSES:
                    raise problem
                reached = True
            wait = waits.next(problem.retry_after)
            if wait is None:
                if waits.attempts > 1:
                    problem.attempts = waits.attempts
                    problem.detail += f" (after {waits.attempts} attempts)"
                raise problem
            if self.on_retry is not None:
                self.on_retry(problem, wait)
            time.sleep(wait)

    def _send(
        self, method: str, route: str, into: Path | None = None, **kwargs: Any
    ) -> httpx.Response:
        """One attempt; ``into``: a successful answer's body is streamed into that file."""
        try:
            if into is None:
                return self._http.request(method, route, **kwargs)
            with self._http.stream(method, route, **kwargs) as answer:
                if answer.is_error:
                    answer.read()
                    return answer
                with open(into, "wb") as file:
                    for chunk in answer.iter_bytes(1 << 20):
                        file.write(chunk)
                return answer
        except httpx.TransportError as error:
            raise Unreachable(f"cannot reach the service at {self.url}: {error}") from error


def float32_bytes(points: np.ndarray | Sequence[Sequence[float]]) -> bytes:
    """(N, 3) points as little-endian float32 ``x y z`` triples, the raw body of ``/align``."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), not {array.shape}")
    return np.ascontiguousarray(array, dtype="<f4").tobytes()


def points_from_bytes(data: bytes) -> np.ndarray:
    """Raw little-endian float32 ``x y z`` triples as an (N, 3) float32 array."""
    return np.frombuffer(data, dtype="<f4").reshape(-1, 3)


def npy_bytes(points: np.ndarray | Sequence[Sequence[float]]) -> bytes:
    """(N, 3) points as an NPY file of little-endian float32: what ``register`` uploads."""
    buffer = io.BytesIO()
    np.save(buffer, np.frombuffer(float32_bytes(points), dtype="<f4").reshape(-1, 3))
    return buffer.getvalue()


def _options(
    viewpoint: Sequence[float] | None,
    candidates: Iterable[str] | None,
    top_k: int | None,
    refine: bool | None,
    min_confidence: float | None,
) -> dict[str, Any]:
    """``/align``'s options as query parameters or form fields; floats written exactly."""
    options: dict[str, Any] = {
        "viewpoint": None if viewpoint is None else ",".join(repr(float(v)) for v in viewpoint),
        "candidates": None if candidates is None else list(candidates),
        "top_k": top_k,
        "refine": None if refine is None else _flag(refine),
        "min_confidence": None if min_confidence is None else repr(float(min_confidence)),
    }
    return {key: value for key, value in options.items() if value is not None}


def _flag(value: bool) -> str:
    return "true" if value else "false"


def _error(answer: httpx.Response) -> ServiceError:
    try:
        detail = str(answer.json()["detail"])
    except (ValueError, KeyError, TypeError):
        detail = answer.text[:200] or answer.reason_phrase
    retry = answer.headers.get("Retry-After")
    return error_for(answer.status_code)(
        detail,
        status=answer.status_code,
        request_id=answer.headers.get("X-Request-ID"),
        retry_after=float(retry) if retry and retry.isdigit() else None,
    )
