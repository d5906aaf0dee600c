"""Train the DPC-MN mapping network without labels (the paper's Sect. 3.2 and 4.A).

    python -m training.train --out runs/shipped            # the objects of training/objects.json
    python -m training.train --mesh-dir my_parts/ --out runs/mine   # any folder of OBJ/STL/PLY
    python -m training.train --out runs/shipped --resume   # go on from the last checkpoint
    torchrun --standalone --nproc_per_node 2 -m training.train --out runs/shipped  # 2 ranks

Reads top to bottom: settings, data, model, optimiser, the loop, checkpoints.
The same code runs on CUDA when present and on the CPU otherwise, in one process or as the
ranks of ``torchrun`` (``training.distributed``: chosen by the environment).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import inspect
import json
import re
import time
import typing
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch.distributed.elastic.multiprocessing.errors import record
from tqdm import tqdm

from training.data import DataConfig, TrainingClouds
from training.distributed import Ranks
from training.losses import total_loss
from training.model import DPCMN, ModelConfig
from training.objects import load_manifest, load_object_meshes, objects_from_folder


@dataclass
class TrainConfig:
    out: str = "runs/shipped"  # the run's folder: checkpoint.pt, config.json, log.csv
    manifest: str | None = None  # default: training/objects.json
    mesh_dir: str | None = None  # train on every mesh in a folder instead
    epochs: int = 100  # passes over the objects
    views_per_epoch: int = 8  # clouds of each object per epoch
    batch: int = 16  # the paper's batch size
    optimizer: Literal["adam", "sgd"] = (
        "adam"  # measured faster than the paper's "sgd" (docs/decisions.md#which-training-ships)
    )
    lr: float = 1e-3  # the paper's learning rate, for both optimisers
    momentum: float = 0.9  # SGD only, the paper's
    margin: float = 1.0  # epsilon of eq. (1)
    weight: float = 0.3  # lambda of eq. (3), the paper's
    seed: int = 0  # the data's draws and the initial weights
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)


# --paper: the paper's setting (Sect. 4.A); flags given with it still win
PAPER = {"rotations": "paper", "canonical": False, "optimizer": "sgd", "shared": 1.0}


def parse_args(argv: list[str] | None = None) -> tuple[TrainConfig, bool]:
    """The run's configuration and ``--resume`` from the command line.

    One flag per field of ``TrainConfig`` and of its nested ``DataConfig`` and ``ModelConfig``
    (``--views-per-epoch``, ``--shared``, ``--widths 64 128 256``), so every flag parsed reaches
    the configuration.
    """
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    dests = {}
    for path, kind, default, comment in config_fields(TrainConfig):
        dests[path[-1]] = dest = ".".join(path)
        options = argument_type(kind)
        if "type" in options:
            options["metavar"] = path[-1].upper()
        flag_name = f"--{path[-1].replace('_', '-')}"
        parser.add_argument(flag_name, dest=dest, default=default, help=comment or "", **options)
    paper = " ".join(flag(name, value) for name, value in PAPER.items())
    parser.add_argument("--paper", action="store_true", help=f"the paper's setting: {paper}")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    args = parser.parse_args(argv)
    if args.paper:  # again, with the paper's values as the defaults: explicit flags win
        parser.set_defaults(**{dests[name]: value for name, value in PAPER.items()})
        args = parser.parse_args(argv)
    values: dict = {}
    for dest in dests.values():
        *groups, name = dest.split(".")
        target = values
        for group in groups:
            target = target.setdefault(group, {})
        target[name] = getattr(args, dest)
    return config_from_dict(values), args.resume


def config_fields(cls: type, path: tuple[str, ...] = ()):
    """``(path, type, default, comment)`` of every field, nested configurations flattened."""
    hints = typing.get_type_hints(cls)
    comments = field_comments(cls)
    for item in dataclasses.fields(cls):
        kind = hints[item.name]
        if dataclasses.is_dataclass(kind):
            yield from config_fields(kind, (*path, item.name))
            continue
        default = item.default
        if default is dataclasses.MISSING:
            default = item.default_factory()
        yield (*path, item.name), kind, default, comments.get(item.name)


def field_comments(cls: type) -> dict[str, str]:
    """The comment on each field's line of the class (``points: int = 1024  # per cloud``)."""
    line = re.compile(r"^\s+(\w+):[^#]*#\s*(.+)$")
    return {m[1]: m[2] for m in map(line.match, inspect.getsource(cls).splitlines()) if m}


def argument_type(kind) -> dict:
    """argparse's keywords for a field of this type."""
    options = [a for a in typing.get_args(kind) if a is not type(None)]
    if kind is bool:
        return {"action": argparse.BooleanOptionalAction}
    if typing.get_origin(kind) is typing.Literal:
        return {"choices": options}
    if typing.get_origin(kind) is tuple:
        return {"type": options[0], "nargs": "+"}
    return {"type": options[0] if options else kind}  # X | None: an X


def flag(name: str, value) -> str:
    """How a value is given on the command line: ``--shared 1.0``, ``--no-canonical``."""
    option = name.replace("_", "-")
    if isinstance(value, bool):
        return f"--{option}" if value else f"--no-{option}"
    return f"--{option} {value}"


def training_objects(config: TrainConfig):
    """The seen objects of the manifest, or every mesh of ``mesh_dir``."""
    if config.mesh_dir:
        return objects_from_folder(Path(config.mesh_dir))
    manifest = Path(config.manifest) if config.manifest else None
    return load_manifest(manifest, split="seen")


def make_optimizer(config: TrainConfig, model: torch.nn.Module) -> torch.optim.Optimizer:
    if config.optimizer == "adam":
        return torch.optim.Adam(model.parameters(), lr=config.lr)
    if config.optimizer == "sgd":
        return torch.optim.SGD(model.parameters(), lr=config.lr, momentum=config.momentum)
    raise ValueError(f"unknown optimizer {config.optimizer!r}: use 'adam' or 'sgd'")


def config_to_dict(config: TrainConfig) -> dict:
    return json.loads(json.dumps(asdict(config)))


def config_from_dict(values: dict, cls: type = TrainConfig):
    """A configuration from its dict (a checkpoint's, or the command line's), nested ones too."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in values.items():
        if dataclasses.is_dataclass(hints.get(name)):
            value = config_from_dict(value, hints[name])
        kwargs[name] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)


def train(config: TrainConfig, resume: bool = False) -> Path:
    out = Path(config.out)
    checkpoint_path = out / "checkpoint.pt"
    ranks = Ranks.from_environment()  # one process, or one rank of torchrun
    device = ranks.device
    torch.manual_seed(config.seed)

    # Data: fresh surface samples of the training objects every epoch.
    specs = training_objects(config)
    clouds = TrainingClouds(load_object_meshes(specs), config.data, config.seed)

    # Model and optimiser, or both as the checkpoint left them (by either kind of run).
    model = DPCMN(config.model).to(device)
    optimizer = make_optimizer(config, model)
    start_epoch = 0
    if resume and checkpoint_path.exists():
        checkpoint = torch.load(checkpoint_path, map_location=device, weights_only=True)
        model.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        start_epoch = checkpoint["epoch"] + 1
    trained = ranks.wrap(model)  # DistributedDataParallel under torchrun
    log_path = out / "log.csv"
    if ranks.main:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(config_to_dict(config), indent=2))
        if start_epoch == 0:
            log_path.write_text("epoch,loss,mapping_loss,pose_loss,seconds\n")

    # The loop: each epoch shows every object views_per_epoch times, in batches; each rank
    # computes its share of every batch (each cloud seeded by its place in the epoch).
    for epoch in range(start_epoch, config.epochs):
        began = time.perf_counter()
        rng = np.random.default_rng([config.seed, epoch])
        clouds.start_epoch(epoch)
        order = rng.permutation(np.repeat(clouds.names, config.views_per_epoch))
        batches = ranks.batches(order, config.batch)
        sums = np.zeros(3)
        trained.train()
        progress = tqdm(
            list(enumerate(batches)),
            desc=f"epoch {epoch + 1}/{config.epochs}",
            leave=False,
            disable=not ranks.main,
        )
        for index, names in progress:
            share = ranks.share(len(names))
            seeds = [[config.seed, epoch, index, k] for k in range(share.start, share.stop)]
            # shared: the rows that are the same surface point in anchor and rotated cloud
            anchor, positive, rotated, shared = (
                torch.from_numpy(part).to(device)
                for part in clouds.batch(list(names[share]), seeds)
            )
            mapped = trained(torch.cat([anchor, positive, rotated]))
            m_a, m_p, m_i = mapped.chunk(3)
            shuffle = torch.Generator().manual_seed(config.seed * 1_000_003 + epoch * 1009 + index)
            m_n = m_a[:, torch.randperm(m_a.shape[1], generator=shuffle).to(device)]  # shuffled
            # anchor: the same permutation on every rank, and after a resume
            # eq. (2) compares the points both clouds hold
            loss, l_m, l_p = total_loss(m_a, m_p, m_n, m_i, config.margin, config.weight, shared)
            weight = ranks.weight(len(names))  # this share's part of the batch's mean
            optimizer.zero_grad()
            (loss * weight).backward()
            optimizer.step()
            sums += np.array([loss.item(), l_m.item(), l_p.item()]) * weight / ranks.world
        means = ranks.total(sums) / len(batches)
        seconds = time.perf_counter() - began
        if not ranks.main:
            continue
        with log_path.open("a", newline="") as log:
            csv.writer(log).writerow([epoch + 1, *np.round(means, 6), round(seconds, 2)])
        tqdm.write(
            f"epoch {epoch + 1}: loss {means[0]:.4f} (L_m {means[1]:.4f}, "
            f"L_p {means[2]:.4f}) {seconds:.1f} s"
            + (f" on {ranks.world} ranks" if ranks.world > 1 else "")
        )

        # Checkpoints carry the model's arguments and the run's config; the bare model's
        # weights, so that one process or any number of ranks resumes them.
        torch.save(
            {
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "epoch": epoch,
                "config": config_to_dict(config),
                "objects": [spec.name for spec in specs],
            },
            checkpoint_path,
        )
    ranks.close()
    return checkpoint_path


@record  # under torchrun, a rank's exception and traceback reach the launcher's error summary
def main(argv: list[str] | None = None) -> None:
    config, resume = parse_args(argv)
    train(config, resume)


if __name__ == "__main__":
    main()
