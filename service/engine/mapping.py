"""Step 2, map: map every point to 2-D with the exported network (onnxruntime).

The CUDA execution provider is used when onnxruntime-gpu and a GPU are present and
``use_cuda`` is set, the CPU provider otherwise. How the network expects its input
(principal-axes frame or not) travels inside the ONNX file as metadata, so a model
and its preprocessing cannot be separated.

The process's BLAS (numpy's and scipy's OpenBLAS) is held to ``blas_threads`` (one) where a
``Mapper`` is made: its spinning workers took the cores from onnxruntime's threads
(docs/decisions.md#speed).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import onnxruntime as ort
from threadpoolctl import threadpool_limits

from service.settings import ModelSettings

INPUT_NAME = "points"  # (1, N, 3) float32, normalised
OUTPUT_NAME = "mapped"  # (1, N, 2) float32


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def limit_blas(threads: int) -> None:
    """Hold every BLAS library loaded in the process (numpy's and scipy's OpenBLAS; torch's
    own is linked in and not seen) to ``threads`` threads, from now on."""
    threadpool_limits(limits=threads, user_api="blas")


class Mapper:
    """The DPC-MN network: normalised (N, 3) points to (N, 2) mapped coordinates."""

    def __init__(
        self,
        path: Path,
        intra_op_threads: int = 1,
        inter_op_threads: int = 1,
        use_cuda: bool = True,
        model_hash: str | None = None,  # when the caller has already read the file
        blas_threads: int | None = 1,  # None leaves the process's BLAS as it is
    ):
        if blas_threads is not None:
            limit_blas(blas_threads)
        options = ort.SessionOptions()
        options.intra_op_num_threads = intra_op_threads
        options.inter_op_num_threads = inter_op_threads
        providers = ["CPUExecutionProvider"]
        if use_cuda and "CUDAExecutionProvider" in ort.get_available_providers():
            providers.insert(0, "CUDAExecutionProvider")
        self.path = Path(path)
        self.session = ort.InferenceSession(str(path), options, providers=providers)
        # a registration's many small clouds: one thread that does not spin while it waits,
        # beside the geometry's thread (the same bits as two threads on clouds of 16 to 4,096
        # points: docs/operations.md, "Registration time")
        quiet = ort.SessionOptions()
        quiet.intra_op_num_threads = quiet.inter_op_num_threads = 1
        quiet.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self._quiet = ort.InferenceSession(str(path), quiet, providers=providers)
        self.providers: list[str] = self.session.get_providers()
        self.model_hash = model_hash or file_sha256(self.path)
        metadata = self.session.get_modelmeta().custom_metadata_map
        self.canonical = metadata.get("canonical", "false") == "true"
        self.metadata = dict(metadata)

    @classmethod
    def from_settings(cls, model: ModelSettings, model_hash: str | None = None) -> Mapper:
        return cls(
            model.path,
            model.intra_op_threads,
            model.inter_op_threads,
            model.use_cuda,
            model_hash,
            model.blas_threads,
        )

    def map(self, normalized: np.ndarray, quiet: bool = False) -> np.ndarray:
        """Mapped coordinates (N, 2) of normalised points (N, 3); ``quiet``: on the
        single-threaded session, for work that runs beside other work (a registration's)."""
        batch = np.ascontiguousarray(normalized, dtype=np.float32)[None]
        session = self._quiet if quiet else self.session
        return session.run([OUTPUT_NAME], {INPUT_NAME: batch})[0][0]
