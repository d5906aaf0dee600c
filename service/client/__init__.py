"""A Python client for the DPC-MN pose service, and the ``dpc-mn`` command line (``cli``).

    from service.client import Client

    with Client("http://127.0.0.1:8000", api_key="...") as client:
        client.register("bracket-a", "bracket.stl")
        pose = client.align(points, viewpoint=[0, 0, 0])  # (N, 3), sent as raw float32
        if pose.is_match:
            grasp(pose.transform)  # scene = R @ model + t
        else:
            print(pose.verdict, pose.reasons)

It needs numpy and httpx only: it never imports the service's engine or API.
"""

from service.client.answers import Alternative, Candidate, Detection, Pose, Reference, Scene
from service.client.client import Client, DepthCamera
from service.client.errors import (
    BadRequest,
    Conflict,
    Forbidden,
    InvalidInput,
    NotFound,
    ServerError,
    ServiceError,
    StorageFull,
    TimedOut,
    TooLarge,
    Unauthorized,
    Unavailable,
    Unreachable,
    UnsupportedMediaType,
)

__all__ = [
    "Alternative",
    "BadRequest",
    "Candidate",
    "Client",
    "Conflict",
    "DepthCamera",
    "Detection",
    "Forbidden",
    "InvalidInput",
    "NotFound",
    "Pose",
    "Reference",
    "Scene",
    "ServerError",
    "ServiceError",
    "StorageFull",
    "TimedOut",
    "TooLarge",
    "Unauthorized",
    "Unavailable",
    "Unreachable",
    "UnsupportedMediaType",
]
