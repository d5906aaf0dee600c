"""The network of Fig. 2 and the losses of eqs. (1)-(3)."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from training.losses import mapping_loss, pose_loss, total_loss  # noqa: E402
from training.model import DPCMN  # noqa: E402


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return DPCMN().eval()


def test_output_is_one_2d_coordinate_per_point(model):
    assert model(torch.randn(2, 300, 3)).shape == (2, 300, 2)


def test_permuting_the_points_permutes_the_output_rows(model):
    points = torch.randn(1, 500, 3)
    order = torch.randperm(500)
    with torch.no_grad():
        assert torch.allclose(model(points)[:, order], model(points[:, order]), atol=1e-5)


def test_output_does_not_depend_on_the_number_of_points_beyond_sampling(model):
    generator = torch.Generator().manual_seed(1)
    dense = torch.nn.functional.normalize(torch.randn(1, 8000, 3, generator=generator), dim=2)
    with torch.no_grad():
        mapped_dense = model(dense)[:, :500]
        mapped_sparse = model(dense[:, :1000])[:, :500]  # the same 500 points in a smaller cloud
    spread = mapped_dense.std()
    assert (mapped_dense - mapped_sparse).norm(dim=2).mean() < 0.05 * spread


def test_mapping_loss_is_zero_when_the_margin_is_met_and_positive_otherwise():
    anchor = torch.tensor([[[0.0, 0.0], [10.0, 0.0]]])
    positive = anchor + 0.01
    negative = anchor.flip(1)  # each row is the other point
    assert mapping_loss(anchor, positive, negative, margin=1.0) == 0
    collapsed = torch.zeros_like(anchor)
    assert torch.isclose(
        mapping_loss(collapsed, collapsed, collapsed, margin=1.0), torch.tensor(1.0)
    )


def test_pose_loss_is_the_mean_distance():
    anchor = torch.zeros(1, 4, 2)
    rotated = torch.tensor([[[3.0, 4.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]])
    assert torch.isclose(pose_loss(anchor, rotated), torch.tensor(5.0 / 4))


def test_pose_loss_over_the_shared_rows_is_their_mean_distance():
    """With a mask, eq. (2) averages over the rows both clouds hold, in every cloud of the batch:
    for the same rows in each cloud it is the mean over those rows."""
    anchor = torch.zeros(2, 4, 2)
    rotated = torch.tensor([[[3.0, 4.0], [0.0, 1.0], [9.0, 9.0], [9.0, 9.0]]]).repeat(2, 1, 1)
    first_two = torch.tensor([True, True, False, False]).repeat(2, 1)
    assert torch.isclose(pose_loss(anchor, rotated, first_two), torch.tensor(3.0))
    assert torch.isclose(
        pose_loss(anchor, rotated, first_two), pose_loss(anchor[:, :2], rotated[:, :2])
    )
    uneven = torch.tensor([[True, False, False, False], [True, True, False, False]])
    assert torch.isclose(pose_loss(anchor, rotated, uneven), torch.tensor((5 + 5 + 1) / 3))


def test_total_loss_weighs_the_pose_term_by_lambda():
    anchor = torch.zeros(1, 4, 2)
    rotated = torch.ones(1, 4, 2)
    f, l_m, l_p = total_loss(anchor, anchor, anchor, rotated, margin=1.0, weight=0.3)
    assert torch.isclose(f, l_m + 0.3 * l_p) and torch.isclose(l_m, torch.tensor(1.0))
