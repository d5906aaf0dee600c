"""Every setting of the service, from environment variables (prefix ``DPC_``).

Grouped by concern; nested groups read ``DPC_<GROUP>__<FIELD>``, e.g.
``DPC_ENGINE__TOP_K=5`` or ``DPC_SERVER__PORT=9000``.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, Field
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parent.parent
MODELS_DIR = REPO_ROOT / "models"


class ModelSettings(BaseModel):
    path: Path = MODELS_DIR / "dpc_mn.onnx"
    manifest: Path = MODELS_DIR / "manifest.json"
    gallery: Path = MODELS_DIR / "gallery.npz"  # seeds the database on first start
    intra_op_threads: int = Field(2, ge=1)
    inter_op_threads: int = Field(1, ge=1)
    use_cuda: bool = True  # CUDA execution provider when onnxruntime-gpu and a GPU are present


class EngineSettings(BaseModel):
    network_points: int = Field(1024, ge=64)  # the observation is subsampled to this many points
    top_k: int = Field(3, ge=1)  # candidates verified geometrically
    hypotheses: tuple[str, ...] = ("mapped", "principal-axes")  # also: "paper"
    ransac_iterations: int = Field(200, ge=1)
    ransac_threshold: float = Field(0.08, gt=0)  # inlier distance, share of the reference's scale
    verify_points: int = Field(256, ge=16)  # subsample for the cheap alignment-error check
    refine_best: int = Field(2, ge=1)  # hypotheses refined with ICP
    icp_iterations: int = Field(20, ge=1)
    icp_points: int = Field(512, ge=16)
    view_grids: int = Field(12, ge=1)  # augmented views per reference for the classifier
    classifier_ridge: float = Field(1e-3, gt=0)
    seed: int = 0


class GallerySettings(BaseModel):
    data_dir: Path = REPO_ROOT / "data"  # the SQLite database lives here
    reference_points: int = Field(2048, ge=64)  # a mesh upload is sampled to this many points
    max_references: int = Field(1000, ge=1)
    self_check_poses: int = Field(3, ge=0)  # poses a registration is checked on (0: no check)


class LimitSettings(BaseModel):
    min_points: int = Field(32, ge=3)
    max_points: int = Field(200_000, ge=1)
    max_body_bytes: int = Field(32 * 1024 * 1024, ge=1024)


class ServerSettings(BaseModel):
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    workers_threads: int = Field(2, ge=1)  # threads that run alignments off the event loop
    log_level: str = "info"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="DPC_", env_nested_delimiter="__")

    model: ModelSettings = ModelSettings()
    engine: EngineSettings = EngineSettings()
    gallery: GallerySettings = GallerySettings()
    limits: LimitSettings = LimitSettings()
    server: ServerSettings = ServerSettings()
