"""``benchmarks.align_http``: its clouds and padding references come from the shipped gallery
(no pybullet), and a tiny run of ``python -m benchmarks.align_http`` against a real
``python -m service`` works with the runtime packages alone. Only what the run produces is
checked, never how long anything took."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from benchmarks.align_http.clouds import CLOUD_POINTS, make_clouds, point_spacing
from benchmarks.align_http.padding import padding_points, padding_references
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.gallery.gallery_file import load_gallery
from tests.servers import MODEL, REPO

pytestmark = pytest.mark.skipif(
    not (MODEL.path.exists() and MODEL.gallery.exists()),
    reason=f"no shipped model and gallery at {MODEL.path}",
)

# what the default run must not need (the train and eval extras)
EXTRAS = ("pybullet", "pybullet_data", "open3d", "torch", "cv2", "matplotlib")


@pytest.fixture(scope="module")
def shipped():
    return load_gallery(MODEL.gallery)[0]


def test_clouds_are_resampled_references_in_the_stated_pose(shipped):
    references = shipped[:2]
    clouds = make_clouds(references, 2, seed=3)
    assert [c.label for c in clouds] == [r.name for r in references] * 2  # interleaved
    again = make_clouds(references, 2, seed=3)
    assert all(a.raw_body == b.raw_body for a, b in zip(clouds, again, strict=True))
    for cloud in clouds:
        reference = next(r for r in references if r.name == cloud.label)
        assert cloud.points.shape == (CLOUD_POINTS, 3)
        raw = np.frombuffer(cloud.raw_body, "<f4").reshape(-1, 3)
        assert np.array_equal(raw, cloud.points)
        sent = np.array(json.loads(cloud.json_body)["points"])
        assert np.abs(sent - cloud.points).max() < 1e-5
        # back in the model frame: on the reference's surface, but none a registered point
        model = (cloud.points.astype(np.float64) - cloud.translation) @ cloud.rotation
        distances, _ = cKDTree(reference.points).query(model)
        spacing = point_spacing(reference.points)
        assert distances.min() > 0
        assert np.median(distances) < spacing


def test_padding_references_are_new_shapes_computed_once_then_cached(shipped, tmp_path):
    base = shipped[:2]

    def profile(points: np.ndarray) -> np.ndarray:  # the same in any pose and at any size
        radii = np.sort(np.linalg.norm(points - points.mean(axis=0), axis=1))
        return radii / radii[-1]

    first, again = (padding_points(base, i)[1] for i in (0, 2))  # one base, twice
    for one, other in ((first, again), (first, base[0].points), (again, base[0].points)):
        assert not np.allclose(profile(one), profile(other), rtol=0.02)
    engine = Engine(Mapper(MODEL.path, 1, 1, False))
    computed, count, seconds = padding_references(engine, base, 1, tmp_path)
    assert count == 1 and seconds is not None and len(computed) == 1 and not computed[0].missing
    assert computed[0].name.startswith("pad-0000-")
    cached, count, seconds = padding_references(engine, base, 1, tmp_path)
    assert count == 0 and seconds is None
    assert cached[0].points_sha256 == computed[0].points_sha256
    assert np.array_equal(cached[0].field, computed[0].field)


@pytest.mark.slow
def test_a_tiny_run_needs_no_extra_and_reports_every_figure(tmp_path):
    out = tmp_path / "bench.json"
    arguments = [
        "--references", "1", "2", "--requests", "3", "--warmup", "1", "--clients", "1", "2",
        "--concurrent-requests", "2", "--clouds-per-object", "1", "--registrations", "1",
        "--refit-references", "2", "--refit-repeats", "1", "--padding-cache", "",
        "--providers", "cpu", "--json", str(out),
    ]  # fmt: skip
    script = (
        "import sys\n"
        "class Missing:  # as if the extras were not installed\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name.split('.')[0] in {EXTRAS!r}:\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, Missing())\n"
        "import runpy\n"
        "from benchmarks.align_http.command import parse_args\n"
        "try:\n"
        "    parse_args(['--accuracy'])\n"
        "except SystemExit as stop:\n"
        "    assert stop.code == 2\n"
        f"sys.argv = ['align_http', *{arguments!r}]\n"
        "runpy.run_module('benchmarks.align_http', run_name='__main__')  # python -m\n"
        f"assert not [m for m in {EXTRAS!r} if m in sys.modules]\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    print(done.stdout[-3000:])
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "--accuracy aligns pybullet's meshes" in done.stderr
    report = json.loads(out.read_text())
    assert [(r["references"], r["provider"]) for r in report["runs"]] == [(1, "cpu"), (2, "cpu")]
    run = report["runs"][1]
    for answers in (run["http_raw"], run["http_json"], run["engine"]):
        assert answers["count"] == 3
        assert {"map", "hypothesise", "refine", "unattributed", "total"} <= set(answers["steps_ms"])
        assert answers["label_right"] > 0.5 and answers["success"] > 0.5
    assert run["http_raw"]["overhead_ms"]["count"] == 3
    levels = [(c["kind"], c["clients"]) for c in run["concurrency"]]
    assert levels == [("raw", 1), ("raw", 2), ("json", 1), ("json", 2)]
    registration = run["registration"]
    assert registration["remove"]["count"] == 2
    assert registration["register_checked"]["count"] == 1 and registration["checks"] >= 1
    assert report["refit"]["references"] == 2
    (growth,) = report["growth"]
    assert (growth["from"], growth["to"]) == (1, 2)
    for paired in (growth["paired"]["http_raw"], growth["paired"]["engine"]):
        assert paired["requests"] == 3 and len(paired["latency"]["median_ms"]) == 2
