"""Training end to end on a tiny set, and the export's self-check."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

from service.engine.mapping import Mapper  # noqa: E402
from training.export import check_parity, export_onnx, load_checkpoint  # noqa: E402
from training.train import main as train_main  # noqa: E402


@pytest.fixture(scope="module")
def mesh_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("meshes")
    trimesh.creation.box(extents=(1, 2, 3)).export(folder / "box.stl")
    trimesh.creation.cylinder(radius=0.5, height=2).export(folder / "cylinder.obj")
    trimesh.creation.annulus(r_min=0.5, r_max=1, height=0.3).export(folder / "ring.ply")
    return folder


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, mesh_dir):
    out = tmp_path_factory.mktemp("run")
    args = [
        "--mesh-dir",
        str(mesh_dir),
        "--out",
        str(out),
        "--epochs",
        "4",
        "--points",
        "128",
        "--views-per-epoch",
        "8",
        "--batch",
        "8",
        "--seed",
        "0",
    ]
    train_main(args)
    return out, args


def read_losses(out):
    with open(out / "log.csv") as log:
        return [float(row["loss"]) for row in csv.DictReader(log)]


def test_a_tiny_training_run_lowers_the_loss(tiny_run):
    out, _ = tiny_run
    losses = read_losses(out)
    assert len(losses) == 4
    assert losses[-1] < losses[0]


def test_the_checkpoint_carries_the_config_and_resumes(tiny_run):
    out, args = tiny_run
    checkpoint = torch.load(out / "checkpoint.pt", weights_only=True)
    assert checkpoint["epoch"] == 3 and checkpoint["config"]["data"]["points"] == 128
    assert sorted(checkpoint["objects"]) == ["box", "cylinder", "ring"]
    train_main([*args[:-4], "--epochs", "5", "--seed", "0", "--resume"])
    assert len(read_losses(out)) == 5  # one more epoch, appended to the same log
    assert json.loads((out / "config.json").read_text())["epochs"] == 5


def test_export_matches_pytorch_and_carries_its_input_convention(tiny_run, tmp_path):
    out, _ = tiny_run
    model, config, _ = load_checkpoint(out / "checkpoint.pt")
    path = tmp_path / "model.onnx"
    export_onnx(model, config.data.canonical, path, {})
    assert check_parity(model, path) < 1e-4
    mapper = Mapper(path, use_cuda=False)
    assert mapper.canonical == config.data.canonical
    assert mapper.providers == ["CPUExecutionProvider"]
    cloud = np.random.default_rng(0).uniform(-1, 1, (777, 3)).astype(np.float32)
    with torch.no_grad():
        expected = model(torch.from_numpy(cloud)[None])[0].numpy()
    assert np.abs(mapper.map(cloud) - expected).max() < 1e-4
