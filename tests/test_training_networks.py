"""Networks: parameter counts, shapes, encode + head == forward."""

import pytest
import torch

from training.networks import GraspQualityNet, count_parameters
from vgq.normalization import Normalization
from vgq.pose import POSE_COLUMNS


@pytest.mark.parametrize("arch, expected", [("vgqcnn", 6.5e6), ("fast_vgqcnn", 6.5e6), ("gqcnn", 5.4e6)])
def test_parameter_count_matches_paper(arch, expected):
    n = count_parameters(GraspQualityNet(arch))
    assert abs(n - expected) / expected < 0.01, n


@pytest.mark.parametrize("arch", sorted(POSE_COLUMNS))
def test_output_shapes(arch):
    net = GraspQualityNet(arch).eval()
    k = 3
    depth = torch.rand(k, 1, 32, 32) + 0.5
    poses = torch.rand(k, len(POSE_COLUMNS[arch]))
    with torch.no_grad():
        assert net(depth, poses).shape == (k, 2)
        assert net.encode(depth).shape == (k, 1024)
        p = net.head(net.encode(depth), poses)
    assert p.shape == (k,) and torch.all((p >= 0) & (p <= 1))


def test_fast_encode_head_equals_forward():
    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn").eval()
    net.set_normalization(
        Normalization(0.7, 0.1, POSE_COLUMNS["fast_vgqcnn"], [0, 0, 0.7, 0, 0, 0, 0], [4, 4, 0.1, 1, 1, 1, 1])
    )
    depth = 0.7 + 0.05 * torch.rand(1, 1, 32, 32)
    poses = torch.randn(5, 7)
    with torch.no_grad():
        one_piece = torch.softmax(net(depth.expand(5, -1, -1, -1), poses), 1)[:, 1]
        split = net.head(net.encode(depth), poses)  # one image term broadcast over 5 grasps
    torch.testing.assert_close(split, one_piece, rtol=1e-5, atol=1e-6)


def test_wider_second_stage_keeps_the_encoder_contract():
    net = GraspQualityNet("fast_vgqcnn", conv2_channels=96).eval()
    assert net.conv2_2.weight.shape == (96, 96, 3, 3) and net.fc3.in_features == 96 * 8 * 8
    assert count_parameters(net) > count_parameters(GraspQualityNet("fast_vgqcnn"))
    with torch.no_grad():
        assert net.encode(torch.rand(2, 1, 32, 32) + 0.5).shape == (2, 1024)  # the service's image term


def test_conv2_channels_must_be_positive():
    with pytest.raises(ValueError, match="conv2_channels"):
        GraspQualityNet("fast_vgqcnn", conv2_channels=0)
