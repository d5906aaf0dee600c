"""Training end to end on a tiny set, the export's self-check, and the command line: every flag
reaches the configuration, and the README's command gives the shipped model's."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import re
import shlex
import subprocess
import sys
import typing

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

from service.engine.mapping import Mapper  # noqa: E402
from service.engine.registration import kabsch  # noqa: E402
from tests.servers import REPO  # noqa: E402
from training.data import DataConfig, TrainingClouds, direction_within  # noqa: E402
from training.export import check_parity, export_onnx, load_checkpoint  # noqa: E402
from training.export import main as export_main  # noqa: E402
from training.model import DPCMN, ModelConfig  # noqa: E402
from training.train import PAPER, config_to_dict, parse_args  # noqa: E402
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


def test_export_of_the_onnx_file_alone(tiny_run, tmp_path):
    out, _ = tiny_run
    export_main(["--checkpoint", str(out / "checkpoint.pt"), "--out", str(tmp_path), "--onnx-only"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dpc_mn.onnx"]
    assert Mapper(tmp_path / "dpc_mn.onnx", use_cuda=False).canonical


def view_clouds(mesh, **settings) -> TrainingClouds:
    clouds = TrainingClouds({"part": mesh}, DataConfig(**settings), seed=0)
    clouds.start_epoch(0)
    return clouds


def test_two_views_share_exactly_the_rows_the_mask_says():
    """Every point both camera views hold is a shared row, in the same place in both clouds."""
    clouds = view_clouds(trimesh.creation.box(extents=(1, 2, 3)), points=256, pool=2048)
    rng = np.random.default_rng(0)
    for _ in range(5):
        anchor, view, shared = clouds.view_pair("part", rng)
        assert anchor.shape == view.shape == (256, 3) and shared.shape == (256,)
        assert 0 < shared.sum() < 256
        np.testing.assert_array_equal(anchor[shared], view[shared])
        held_by_both = set(map(tuple, anchor)) & set(map(tuple, view))
        assert held_by_both == set(map(tuple, anchor[shared]))
        pool = set(map(tuple, clouds.pools["part"]))
        assert set(map(tuple, anchor)) <= pool and set(map(tuple, view)) <= pool


def test_a_view_is_what_one_camera_sees_and_the_second_camera_is_near_the_first():
    """On a sphere, one camera 4-8 radii away sees a cap of less than half the surface (hidden-
    point removal keeps a few points past the cap's rim: 3-4 % of 8,192 on a sphere); the
    second camera's cap is centred within view_angle of the first's."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    clouds = view_clouds(sphere, points=256, pool=8192, view_angle=60.0)
    rng = np.random.default_rng(1)
    for _ in range(5):
        anchor, view, _ = clouds.view_pair("part", rng)
        axes = []
        for cloud in (anchor, view):
            axis = cloud.mean(axis=0) / np.linalg.norm(cloud.mean(axis=0))
            assert np.mean(cloud @ axis > 0.0) > 0.95  # a cap: (almost) none of the far half
            axes.append(axis)
        assert np.degrees(np.arccos(np.clip(axes[0] @ axes[1], -1, 1))) < 60.0 + 5.0


def test_a_view_with_fewer_points_than_a_cloud_is_padded_with_its_own():
    """A camera sees about half of a sphere's 2,048 points: 1,600 rows need repeats."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    clouds = view_clouds(sphere, points=1600, pool=2048)
    anchor, view, shared = clouds.view_pair("part", np.random.default_rng(2))
    assert anchor.shape == view.shape == (1600, 3)
    assert len(np.unique(anchor, axis=0)) < 1400 and len(np.unique(view, axis=0)) < 1400
    np.testing.assert_array_equal(anchor[shared], view[shared])


def test_a_view_paired_with_the_whole_surface():
    """With view_partner "whole", the second cloud is a uniform subsample of the whole pool:
    it holds points of every side, and shares with the anchor the view's points it kept."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    clouds = view_clouds(sphere, points=256, pool=8192, view_partner="whole")
    anchor, whole, shared = clouds.view_pair("part", np.random.default_rng(6))
    np.testing.assert_array_equal(anchor[shared], whole[shared])
    axis = anchor.mean(axis=0) / np.linalg.norm(anchor.mean(axis=0))
    assert np.mean(anchor @ axis > 0) > 0.95 and 0.3 < np.mean(whole @ axis > 0) < 0.7
    assert 0 < shared.sum() < 256


def test_the_shared_rows_of_a_single_view_triplet_are_one_surface_in_two_poses():
    """After each cloud's own normalisation (canonical frame, radius) and the rotation, the
    shared rows of anchor and rotated cloud differ by a rotation, a shift and a scale only."""
    clouds = view_clouds(
        trimesh.creation.box(extents=(1, 2, 3)), points=256, pool=2048, single_views=1.0
    )
    rng = np.random.default_rng(3)
    for _ in range(5):
        anchor, positive, rotated, shared = clouds.triplet("part", rng)
        assert anchor.dtype == rotated.dtype == np.float32
        a, r = anchor[shared].astype(np.float64), rotated[shared].astype(np.float64)
        scale = np.sqrt(((r - r.mean(0)) ** 2).sum() / ((a - a.mean(0)) ** 2).sum())
        rotation, translation = kabsch(a * scale, r)
        residual = np.abs(a * scale @ rotation.T + translation - r).max()
        assert residual < 1e-4
        assert np.abs(positive - anchor).max() > 0  # eq. (1)'s positive is the jittered anchor


def test_single_views_mix_with_full_clouds_in_one_batch():
    clouds = view_clouds(
        trimesh.creation.box(extents=(1, 2, 3)), points=128, pool=1024, single_views=0.5
    )
    anchor, positive, rotated, shared = clouds.batch(["part"] * 16, [[4, k] for k in range(16)])
    assert anchor.shape == positive.shape == rotated.shape == (16, 128, 3)
    assert shared.shape == (16, 128) and shared.dtype == bool
    full = (shared.sum(axis=1) == clouds.shared_rows) & shared[:, : clouds.shared_rows].all(1)
    assert 0 < full.sum() < 16  # some whole-surface triplets, some camera views


def test_directions_within_a_cone_are_within_it():
    rng = np.random.default_rng(5)
    axis = np.array([0.0, 0.6, 0.8])
    angles = [np.degrees(np.arccos(direction_within(axis, 60.0, rng) @ axis)) for _ in range(500)]
    assert max(angles) <= 60.0 + 1e-6 and min(angles) < 20.0


def test_a_training_run_with_single_views(mesh_dir, tmp_path):
    argv = ["--mesh-dir", str(mesh_dir), "--out", str(tmp_path), "--epochs", "2"]
    argv += ["--points", "128", "--views-per-epoch", "4", "--batch", "4", "--single-views", "0.5"]
    train_main(argv)
    losses = read_losses(tmp_path)
    assert len(losses) == 2 and all(np.isfinite(losses))
    config = json.loads((tmp_path / "config.json").read_text())
    assert config["data"]["single_views"] == 0.5 and config["data"]["view_angle"] == 60.0


def leaves(config, path=()):
    """``(path, value)`` of every field of a configuration, nested ones flattened."""
    for item in dataclasses.fields(config):
        value = getattr(config, item.name)
        if dataclasses.is_dataclass(value):
            yield from leaves(value, (*path, item.name))
        else:
            yield (*path, item.name), value


def other_value(config, path, value):
    """A value of the field's type that is not its default."""
    owner = config
    for name in path[:-1]:
        owner = getattr(owner, name)
    kind = typing.get_type_hints(type(owner))[path[-1]]
    if typing.get_origin(kind) is typing.Literal:
        return next(choice for choice in typing.get_args(kind) if choice != value)
    if isinstance(value, bool):
        return not value
    if isinstance(value, int | float):
        return value + 3 if isinstance(value, int) else value + 0.25
    if isinstance(value, tuple):
        return (8, 16)
    return "somewhere/else"  # str, or str | None


def as_flags(path, value) -> list[str]:
    option = "--" + path[-1].replace("_", "-")
    if isinstance(value, bool):
        return [option if value else "--no-" + option[2:]]
    if isinstance(value, tuple):
        return [option, *map(str, value)]
    return [option, str(value)]


def test_every_flag_reaches_the_configuration():
    defaults, _ = parse_args([])
    fields = list(leaves(defaults))
    assert len(fields) >= 20  # the training, data and model configurations
    argv, expected = [], {}
    for path, value in fields:
        expected[path] = other_value(defaults, path, value)
        argv += as_flags(path, expected[path])
    config, resume = parse_args(argv)
    assert not resume
    assert dict(leaves(config)) == expected
    assert parse_args(["--resume"])[1]


def test_paper_sets_everything_it_says():
    config, _ = parse_args(["--paper"])
    values = {path[-1]: value for path, value in leaves(config)}
    assert PAPER["shared"] == 1.0 and PAPER["canonical"] is False
    assert {name: values[name] for name in PAPER} == PAPER
    # the paper's data with Adam: a flag given with --paper wins
    config, _ = parse_args(["--paper", "--optimizer", "adam"])
    assert config.optimizer == "adam" and config.data.shared == 1.0
    assert config.data.rotations == "paper" and not config.data.canonical


# Data fields added after the shipped run, with the value that trains as it did: its manifest
# has no entry for them
NEWER_THAN_THE_SHIPPED_RUN = {"single_views": 0.0}
AT_ANY_VALUE = {"view_angle", "view_partner"}  # only read when single_views > 0


def readme_training_command() -> list[str]:
    """The arguments of the README's ``python -m training.train`` line."""
    readme = (REPO / "README.md").read_text()
    lines = [line for line in readme.splitlines() if "-m training.train " in line]
    assert len(lines) == 1, lines
    words = shlex.split(lines[0])
    return words[words.index("training.train") + 1 :]


def test_the_readmes_training_command_gives_the_shipped_configuration():
    """Run as written, the README's command trains with the configuration the manifest records."""
    manifest = json.loads((REPO / "models" / "manifest.json").read_text())
    config, resume = parse_args(readme_training_command())
    assert not resume
    values = config_to_dict(config)
    for name, value in NEWER_THAN_THE_SHIPPED_RUN.items():
        assert name not in manifest["training"]["data"]
        assert values["data"].pop(name) == value
    for name in AT_ANY_VALUE:
        values["data"].pop(name)
    assert values == manifest["training"]
    # the run was stopped early: the README says after how many epochs
    trained = manifest["trained_epochs"]
    readme = (REPO / "README.md").read_text()
    if trained != config.epochs:
        assert f'"trained_epochs": {trained}' in readme
    assert re.search(rf"\b{trained} epochs \(", readme), "the README's epochs and timing"


def test_two_ranks_match_one_process_and_resume_either_way(mesh_dir, tmp_path):
    """torchrun with two CPU ranks (gloo), each on half of every batch, takes the steps one
    process takes on the whole batch: three epochs in one process end where one epoch in one
    process, the second under torchrun (resuming the first's checkpoint) and the third in one
    process again (resuming torchrun's) end."""
    common = [
        "--mesh-dir",
        str(mesh_dir),
        "--points",
        "64",
        "--views-per-epoch",
        "4",
        "--batch",
        "5",  # 12 clouds an epoch: batches of 5, 5 and 2; shares of 2 and 3, 1 and 1
        "--seed",
        "3",
        "--optimizer",  # linear in the gradients: rounding differences stay rounding-sized
        "sgd",  # (Adam scales a near-zero gradient's noise up to a whole step)
        "--lr",
        "0.05",
    ]
    single, turns = tmp_path / "single", tmp_path / "turns"
    train_main([*common, "--out", str(single), "--epochs", "3"])
    train_main([*common, "--out", str(turns), "--epochs", "1"])
    torchrun(*common, "--out", str(turns), "--epochs", "2", "--resume")
    train_main([*common, "--out", str(turns), "--epochs", "3", "--resume"])
    first = torch.load(single / "checkpoint.pt", weights_only=True)
    second = torch.load(turns / "checkpoint.pt", weights_only=True)
    assert first["epoch"] == second["epoch"] == 2
    initial = DPCMN(ModelConfig()).state_dict()
    for name, weights in first["model"].items():
        torch.testing.assert_close(second["model"][name], weights, rtol=1e-5, atol=1e-6)
        assert not torch.equal(weights, initial[name]) or weights.dim() == 0, name  # it trained
    losses = read_losses(turns)
    assert len(losses) == 3  # each epoch logged once, whoever ran it
    np.testing.assert_allclose(read_losses(single), losses, rtol=1e-4)


def torchrun(*args: str) -> None:
    """``python -m training.train`` as two CPU ranks of torchrun."""
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc_per_node", "2", "-m", "training.train", *args]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    # the whole of stderr: a failed rank's own error comes before torchrun's long summary
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
