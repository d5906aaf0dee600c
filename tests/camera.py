"""What a depth camera gives, for the tests: a mesh's depth image rendered by a z-buffer.

The camera of docs/evaluation-protocol.md's sensor family: 320x240 pixels, focal length 300 px,
at the origin looking along +z (x right, y down). The surface is sampled densely and each pixel
keeps its nearest sample, so each pixel's depth lies on the surface within about half a pixel.
"""

from __future__ import annotations

import numpy as np
import trimesh

from service.engine.sampling import sample_surface

WIDTH, HEIGHT, FOCAL = 320, 240, 300.0
CX, CY = (WIDTH - 1) / 2, (HEIGHT - 1) / 2
INTRINSICS = {"fx": FOCAL, "fy": FOCAL, "cx": CX, "cy": CY}


def depth_image(
    mesh: trimesh.Trimesh, rotation: np.ndarray, translation: np.ndarray, samples: int = 400_000
) -> np.ndarray:
    """(HEIGHT, WIDTH) float32 depth in metres of the mesh at the pose; 0 where no surface."""
    scene = sample_surface(mesh, samples, seed=1).astype(np.float64) @ rotation.T + translation
    u = np.rint(FOCAL * scene[:, 0] / scene[:, 2] + CX).astype(int)
    v = np.rint(FOCAL * scene[:, 1] / scene[:, 2] + CY).astype(int)
    inside = (u >= 0) & (u < WIDTH) & (v >= 0) & (v < HEIGHT) & (scene[:, 2] > 0)
    pixel, depth = (v * WIDTH + u)[inside], scene[inside, 2]
    order = np.lexsort((depth, pixel))  # by pixel, nearest first
    first = np.unique(pixel[order], return_index=True)[1]
    image = np.zeros(WIDTH * HEIGHT, dtype=np.float32)
    image[pixel[order][first]] = depth[order][first]
    return image.reshape(HEIGHT, WIDTH)


def unproject(depth: np.ndarray) -> np.ndarray:
    """The pinhole model written out: the camera-frame points of the pixels with a depth."""
    rows, columns = np.nonzero(depth > 0)
    z = depth[rows, columns].astype(np.float64)
    return np.stack([(columns - CX) * z / FOCAL, (rows - CY) * z / FOCAL, z], axis=1)
