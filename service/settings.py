"""Every setting of the service, from environment variables (prefix ``DPC_``).

Grouped by concern; nested groups read ``DPC_<GROUP>__<FIELD>``, e.g.
``DPC_ENGINE__TOP_K=5`` or ``DPC_SERVER__PORT=9000``.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parent.parent
MODELS_DIR = REPO_ROOT / "models"


class ModelSettings(BaseModel):
    path: Path = MODELS_DIR / "dpc_mn.onnx"
    manifest: Path | None = None  # default: manifest.json beside the model file
    gallery: Path = MODELS_DIR / "gallery.npz"  # seeds the database on first start
    confidence: Path | None = None  # default: confidence.json beside the model file
    # POST /detect's detections; default: detect_confidence.json beside the model file
    detect_confidence: Path | None = None
    # onnxruntime's threads for one forward: a second spins while it waits and takes the core
    # from the other alignment's Python (docs/decisions.md#at-camera-scale)
    intra_op_threads: int = Field(1, ge=1)
    inter_op_threads: int = Field(1, ge=1)
    # threads of numpy's and scipy's BLAS (OpenBLAS) in the process: its idle workers spin
    # and took the cores from onnxruntime's (``service.engine.mapping.limit_blas``)
    blas_threads: int = Field(1, ge=1)
    use_cuda: bool = True  # CUDA execution provider when onnxruntime-gpu and a GPU are present


class EngineSettings(BaseModel):
    # a cloud of more points is answered from a random sample of this many: the cost stays flat
    # in the cloud's size (docs/decisions.md#at-camera-scale)
    align_points: int = Field(8192, ge=1024)
    network_points: int = Field(1024, ge=64)  # the observation is subsampled to this many points
    top_k: int = Field(3, ge=1)  # candidates eq. (4) proposes for geometric verification
    # observed radius / reference scale of a plausible candidate (full views: 0.96-1.05,
    # one camera's view: 0.85-1.45, measured); (0, inf) turns the size check off
    size_ratio: tuple[float, float] = (0.7, 1.6)
    # observed radius / a rendered view's radius for that view to be proposed
    view_size_ratio: tuple[float, float] = (0.8, 1.25)
    # one or more of service.engine.hypotheses.SOURCES (checked at start)
    hypotheses: tuple[str, ...] = ("views", "principal-axes", "mapped")
    views: int = Field(100, ge=4)  # single-camera views rendered per reference
    view_candidates: int = Field(6, ge=1)  # parts the nearest rendered views propose
    # ... and the next this many, searched where none of the first fits well (0: never)
    more_views: int = Field(4, ge=0)
    # a candidate's hypotheses kept by the quick first look (docs/decisions.md#speed)
    screened: int = Field(12, ge=1)
    ransac_iterations: int = Field(200, ge=1)  # at most; fewer once an all-inlier draw is sure
    ransac_threshold: float = Field(0.08, gt=0)  # inlier distance, share of the reference's scale
    tolerance: float = Field(0.04, gt=0)  # fit and coverage distance, share of the scale
    verify_points: int = Field(64, ge=16)  # observed points in the first, cheap check
    coverage_points: int = Field(64, ge=16)  # expected-visible points in the cheap check
    excellent: float = Field(0.9, gt=0, le=1)  # fit x coverage that ends the search early
    # the confidence of a "match" (a request's min_confidence overrides); default: the
    # calibration's, the lowest at which 99.5 % of the matches it was fitted on were right
    accept: float | None = Field(None, ge=0, le=1)
    reject_below: float = Field(0.2, ge=0, le=1)  # below it "no_match", else "uncertain"
    # after the single views, a best refined fit x coverage under this ends the search: no
    # mapped pairs, no flips or near-symmetries (docs/decisions.md#at-camera-scale); 0: never
    hopeless: float = Field(0.3, ge=0, le=1)
    # the mapped pairs are searched only after single views whose best refined fit x coverage
    # reaches this (docs/decisions.md#at-camera-scale); 0: always
    mapped_from: float = Field(0.7, ge=0, le=1)
    # a cloud no camera told of that hides at least this share of its points from every side
    # (visibility.hidden_share) is a whole part's: no single views are searched for it
    # (docs/decisions.md#a-whole-parts-cloud); 1: always searched
    whole_hidden: float = Field(0.17, ge=0, le=1)
    refine_best: int = Field(4, ge=1)  # hypotheses refined with ICP (at most 2 a part)
    icp_iterations: int = Field(12, ge=1)
    # when no refined hypothesis fits well, the best two of this many more parts are refined
    # (on half the ICP budget; docs/decisions.md#refine); 0: off
    rescued_parts: int = Field(4, ge=0)
    # the best pose turned by its part's near-symmetries: this many of the turned poses nearest
    # the surface are refined, and the one nearest after refining answered (0: not tried)
    near_refined: int = Field(3, ge=0)
    # where no reading fits well and the viewpoint is known, one more: the part in a bin, its
    # floor and walls set aside (docs/decisions.md#a-part-in-a-bin); false: not tried
    bin_walls: bool = True
    # the engine's innermost loops compiled where numba (the fast extra) is installed;
    # false: numpy's, the same poses within 1e-7 (docs/decisions.md#compiled-loops)
    compiled: bool = True
    icp_points: int = Field(384, ge=16)
    # the answer's refinement, where it had not settled, continued for this many iterations on
    # every observed point (0: not); see Search.polish
    polish_iterations: int = Field(24, ge=0)
    view_grids: int = Field(32, ge=1)  # augmented full views per reference for eq. (4)
    partial_views: float = Field(0.0, ge=0, le=1)  # share of them seen by a single camera
    classifier_ridge: float = Field(1e-3, gt=0)
    grid_blur: float = Field(2.0, ge=0)  # Gaussian smoothing of grids before eq. (4), in bins
    mesh_surface_points: int = Field(12000, ge=1000)  # a mesh's dense sample for its views
    seed: int = 0


class GallerySettings(BaseModel):
    data_dir: Path = REPO_ROOT / "data"  # the SQLite database lives here
    # postgresql://user:password@host:5432/database: the gallery in PostgreSQL, shared by every
    # replica that names it; none: SQLite in data_dir
    url: str | None = Field(None, repr=False)
    poll_s: float = Field(0.25, gt=0)  # how often a replica checks for others' changes anyway
    listen: bool = True  # PostgreSQL LISTEN/NOTIFY (off behind a pooler in transaction mode)
    pool_size: int = Field(4, ge=1)  # PostgreSQL connections per replica
    # how long a request waits for a PostgreSQL connection while the database is out of reach
    # (a registration then answers 503 with the reason; an alignment never waits for it)
    connect_timeout_s: float = Field(5.0, gt=0)
    reference_points: int = Field(2048, ge=64)  # a mesh upload is sampled to this many points
    max_references: int = Field(1000, ge=1)
    self_check_poses: int = Field(3, ge=0)  # poses a registration is checked on (0: no check)

    @field_validator("url")
    @classmethod
    def _a_postgresql_url(cls, url: str | None) -> str | None:
        if url and not url.startswith(("postgresql://", "postgres://")):
            raise ValueError("a postgresql://user:password@host:5432/database URL")
        return url or None


class LimitSettings(BaseModel):
    min_points: int = Field(32, ge=3)
    # valid points of a cloud or frame: a 2,048 x 1,536 camera's (missing pixels not counted)
    max_points: int = Field(2048 * 1536, ge=1)
    # a 2,048 x 1,536 binary PCD of x y z rgb floats (binary_compressed: less)
    max_body_bytes: int = Field(64 * 1024 * 1024, ge=1024)
    # the bulk routes' body: a batch of parts (POST /references/batch), a gallery's backup or
    # export (POST /gallery/restore, /gallery/import: about 0.6 MB a reference)
    max_bulk_bytes: int = Field(1024 * 1024 * 1024, ge=1024)
    request_timeout_s: float = Field(30.0, gt=0)  # the engine's work for one request; then 504
    max_concurrent_align: int | None = Field(None, ge=1)  # default: Settings.align_slots
    queue_timeout_s: float = Field(5.0, ge=0)  # wait for a free slot; then 503 + Retry-After


Role = Literal["read", "admin"]  # read: align and list; admin: also register and delete
KEY_PATTERN = re.compile(r"^[\x21-\x7e]+$")  # what a header carries: visible ASCII, no spaces


class AuthSettings(BaseModel):
    # API key -> role, e.g. DPC_AUTH__KEYS='{"<key>": "admin"}'; none: the service is open
    keys: dict[str, Role] = Field(default_factory=dict, repr=False)
    require_key_for_reads: bool = True  # false: align and list without a key

    @field_validator("keys")
    @classmethod
    def _keys_fit_in_a_header(cls, keys: dict[str, Role]) -> dict[str, Role]:
        if not all(KEY_PATTERN.match(key) for key in keys):
            raise ValueError("an API key is visible ASCII characters without spaces")
        return keys


LogLevel = Literal["critical", "error", "warning", "info", "debug"]


def lower(value: object) -> object:
    return value.lower() if isinstance(value, str) else value


class ServerSettings(BaseModel):
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    workers_threads: int = Field(2, ge=1)  # threads that run alignments off the event loop
    # processes that run /align and /detect, each with the model and a copy of the gallery
    # (docs/decisions.md#a-second-core); 0: all in the service's own process; default: one a
    # core this process may use, at most AUTO_ENGINE_PROCESSES, none on a single core
    engine_processes: int | None = Field(None, ge=0, le=64)
    # a request that finds no other in the engine is answered in the service's own process:
    # no hop to a worker (docs/decisions.md#a-second-core); false: every one to the workers
    idle_in_process: bool = True
    log_level: Annotated[LogLevel, BeforeValidator(lower)] = "info"  # INFO reads as info
    log_format: Literal["json", "text"] = "json"  # json: one object a line


AUTO_ENGINE_PROCESSES = 4  # each holds ~240 MB and a copy of the gallery
CGROUP_CPU = (  # a container's CPU limit: cgroup v2, then v1 (quota, period in microseconds)
    (Path("/sys/fs/cgroup/cpu.max"), None),
    (Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us"), Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us")),
)


def usable_cores(limits: tuple | None = None) -> int:
    """The cores this process may use: those it may run on, at most its container's CPU limit
    (a pod limited to 2 CPUs on a 64-core node sees 64 in its affinity)."""
    limits = CGROUP_CPU if limits is None else limits
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cores = cores or 1
    for first, second in limits:
        try:
            words = first.read_text().split()
            quota, period = words[0], (words[1] if second is None else second.read_text().strip())
            if quota not in ("max", "-1"):
                return max(1, min(cores, math.ceil(int(quota) / int(period))))
        except (OSError, ValueError, IndexError, ZeroDivisionError):
            continue
    return cores


JOBS_PER_PROCESS = 2  # alignment slots a worker process: the next job queued while one runs
OPEN_RECENT_ALIGNMENTS = 20


class ConsoleSettings(BaseModel):
    enabled: bool = True  # the web console at /ui (static files; it calls the API like a client)
    # alignments kept in memory for the console to replay (their points and answers); default:
    # 20 while the service is open (no API key: a bench), 0 once keys are set (production)
    recent_alignments: int | None = Field(None, ge=0, le=1000)


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="DPC_", env_nested_delimiter="__")

    model: ModelSettings = ModelSettings()
    engine: EngineSettings = EngineSettings()
    gallery: GallerySettings = GallerySettings()
    limits: LimitSettings = LimitSettings()
    server: ServerSettings = ServerSettings()
    auth: AuthSettings = AuthSettings()
    console: ConsoleSettings = ConsoleSettings()

    @property
    def confidence_path(self) -> Path:
        """The confidence calibration: ``model.confidence``, else ``confidence.json`` beside
        the model."""
        return self.model.confidence or self.model.path.parent / "confidence.json"

    @property
    def detect_confidence_path(self) -> Path:
        """The detections' calibration: ``model.detect_confidence``, else
        ``detect_confidence.json`` beside the model."""
        return self.model.detect_confidence or self.model.path.parent / "detect_confidence.json"

    @property
    def manifest_path(self) -> Path:
        """The model's manifest: ``model.manifest``, else ``manifest.json`` beside the model."""
        return self.model.manifest or self.model.path.parent / "manifest.json"

    @property
    def recent_alignments(self) -> int:
        """How many alignments the service keeps for replay (``console.recent_alignments``)."""
        chosen = self.console.recent_alignments
        return chosen if chosen is not None else (0 if self.auth.keys else OPEN_RECENT_ALIGNMENTS)

    @property
    def engine_processes(self) -> int:
        """How many worker processes run ``/align`` and ``/detect`` (``server.engine_processes``;
        by default one a usable core, at most ``AUTO_ENGINE_PROCESSES``, 0 on one core)."""
        chosen = self.server.engine_processes
        if chosen is not None:
            return chosen
        cores = usable_cores()
        return min(cores, AUTO_ENGINE_PROCESSES) if cores > 1 else 0

    @property
    def align_slots(self) -> int:
        """How many alignments may run at once: by default one a thread, and two a worker
        process (one waiting while the other is answered: docs/decisions.md#a-second-core)."""
        return self.limits.max_concurrent_align or max(
            self.server.workers_threads, JOBS_PER_PROCESS * self.engine_processes
        )
