"""Networks: parameter counts, shapes, encode + head == forward."""

import numpy as np
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


def _centre_net(**kw):
    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", depth_reference="centre", **kw).eval()
    cols = POSE_COLUMNS["fast_vgqcnn"]
    net.set_normalization(
        Normalization(0.01, 0.03, cols, [0, 0, 0.7, 0, 0, 0, 0], [4, 4, 0.1, 1, 1, 1, 1], "centre", 0.7, 0.15)
    )
    return net


def test_centre_reference_sees_the_relief_and_passes_the_depth_on_linearly():
    net = _centre_net()
    depth = 0.7 + 0.05 * torch.rand(3, 1, 32, 32)
    with torch.no_grad():
        shift = net.encode(depth + 0.2) - net.encode(depth)  # the same relief 20 cm further away
        expected = net.fc4_ref.weight[:, 0] * (0.2 / 0.15)
    torch.testing.assert_close(shift, expected.expand(3, -1), rtol=1e-4, atol=1e-5)


def test_centre_reference_is_the_mean_of_the_central_block():
    from vgq.normalization import REFERENCE_PIXELS, window_reference

    x = np.zeros((2, 1, 32, 32), np.float32)
    lo = (32 - REFERENCE_PIXELS) // 2
    x[0, 0, lo : lo + REFERENCE_PIXELS, lo : lo + REFERENCE_PIXELS] = 0.5
    x[1] = 0.9
    np.testing.assert_allclose(window_reference(x), [0.5, 0.9], rtol=1e-6)


def test_normalisation_of_relative_crops_from_data():
    from vgq.normalization import window_reference

    rng = np.random.default_rng(0)
    x = (0.5 + rng.random((40, 1, 32, 32)) * 0.5).astype(np.float32)
    norm = Normalization.from_data(x, rng.random((40, 7)), POSE_COLUMNS["fast_vgqcnn"], "centre")
    ref = window_reference(x)
    rel = x - ref[:, None, None, None]
    assert norm.image_reference == "centre"
    np.testing.assert_allclose([norm.image_mean, norm.image_std], [rel.mean(), rel.std()], rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose([norm.reference_mean, norm.reference_std], [ref.mean(), ref.std()], rtol=1e-5)
    assert Normalization.from_dict(norm.to_dict()) == norm
    with pytest.raises(ValueError, match="image_reference"):
        GraspQualityNet("fast_vgqcnn").set_normalization(norm)  # a net that reads absolute depth


def test_rotation_pose_features_are_the_quaternions_matrix():
    from scipy.spatial.transform import Rotation

    from training.networks import rotation_entries

    r = Rotation.random(6, random_state=0)
    xyzw = r.as_quat()
    q = torch.tensor(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1))  # w, x, y, z
    np.testing.assert_allclose(rotation_entries(q).numpy().reshape(6, 3, 3), r.as_matrix(), atol=1e-12)
    net = GraspQualityNet("fast_vgqcnn", pose_features="rotation", pose_units=64)
    assert net.pc1.in_features == 3 + 9 and net.fc4_pose.in_features == 64
    with pytest.raises(ValueError, match="quaternion"):
        GraspQualityNet("gqcnn", pose_features="rotation")


def _jaw_net():
    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw").eval()
    torch.nn.init.normal_(net.roi_fc2.weight, std=0.1)  # a trained head, not its zero start
    return net


def test_jaw_grid_head_one_window_for_k_grasps_equals_k_copies():
    net = _jaw_net()
    depth = 0.6 + 0.1 * torch.rand(1, 1, 32, 32)
    q = torch.nn.functional.normalize(torch.randn(6, 4), dim=1)
    poses = torch.cat([torch.rand(6, 2) * 24 - 12, 0.5 + 0.3 * torch.rand(6, 1), q], 1)
    with torch.no_grad():
        encoding = net.encode(depth)
        assert encoding.shape == (1, net.encoding_width) == (1, 1024 + 64 * 16 * 16)
        shared = net.head_logits(encoding, poses)
        copies = net(depth.expand(6, -1, -1, -1).contiguous(), poses)
    torch.testing.assert_close(shared, copies, rtol=1e-5, atol=1e-5)


def test_jaw_grid_lies_along_the_jaw_in_metres_at_the_grasps_depth():
    net = _jaw_net()
    turn = np.pi / 2  # 90 deg about the optical axis: the jaw axis (the rotation's x column) along +v
    poses = torch.tensor([[2.0, -3.0, 0.7, np.cos(turn / 2), 0, 0, np.sin(turn / 2)]], dtype=torch.float32)
    pts = net.jaw_grid_points(poses)[0] * 16  # crop px from the crop's centre
    middle = pts[:, 1]  # the row across the jaw's middle
    torch.testing.assert_close(middle[:, 0], torch.full((8,), 2.0))
    per_metre = 525.0 / 3 / 0.7
    torch.testing.assert_close(middle[:, 1], -3.0 + per_metre * torch.linspace(-0.04, 0.04, 8))


def test_jaw_grid_head_reads_the_image_at_the_grasp():
    net = _jaw_net()
    flat = torch.full((1, 1, 32, 32), 0.7)
    bumped = flat.clone()
    bumped[..., 2:8, 2:8] -= 0.05  # a bump in the window's top-left corner
    on_bump = torch.tensor([[-10.0, -10.0, 0.7, 1, 0, 0, 0]])  # a grasp there (crop px from the centre)
    far = torch.tensor([[10.0, 10.0, 0.7, 1, 0, 0, 0]])  # one in the opposite corner
    with torch.no_grad():
        f0, f1 = (net.encode(d)[:, 1024:].reshape(1, 256, 64) for d in (flat, bumped))
        seen = (net.roi_term(f1, on_bump) - net.roi_term(f0, on_bump)).abs().max()
        unseen = (net.roi_term(f1, far) - net.roi_term(f0, far)).abs().max()
    assert unseen < 1e-6 < seen


def test_jaw_grid_reads_are_grid_samples_bilinear_border_reads():
    net = _jaw_net()
    fmap = torch.randn(3, 64, 16, 16)
    q = torch.nn.functional.normalize(torch.randn(3, 4), dim=1)
    poses = torch.cat(
        [torch.tensor([[0.0, 0.0], [11.9, -12.0], [30.0, 2.5]]), torch.tensor([[0.7], [0.45], [1.0]]), q], 1
    )
    grid = net.jaw_grid_points(poses)  # the third grasp's grid leaves the map: border reads
    ref = torch.nn.functional.grid_sample(fmap, grid, align_corners=False, padding_mode="border").reshape(3, -1)
    with torch.no_grad():
        got = net.roi_term(fmap.permute(0, 2, 3, 1).reshape(3, 256, 64), poses)
        want = net.roi_fc2(torch.relu(net.roi_fc1(ref)))
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


def test_jaw_depth_head_reads_the_crops_depth_relative_to_the_grasp():
    """ "jaw_depth": the encoding also carries the crop; the head reads it at the grid points as
    depth relative to the grasp's z (grid_sample's bilinear border reads, in cm), one window for
    k grasps as k copies."""
    from training.networks import JAW_DEPTH_SCALE

    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw_depth").eval()
    torch.nn.init.normal_(net.roi_fc2.weight, std=0.1)
    depth = 0.6 + 0.1 * torch.rand(1, 1, 32, 32)
    q = torch.nn.functional.normalize(torch.randn(5, 4), dim=1)
    poses = torch.cat([torch.rand(5, 2) * 40 - 20, 0.5 + 0.3 * torch.rand(5, 1), q], 1)
    with torch.no_grad():
        enc = net.encode(depth)
        assert enc.shape == (1, net.encoding_width) == (1, 1024 + 64 * 16 * 16 + 32 * 32)
        torch.testing.assert_close(net.encoding_crop(enc).reshape(1, 1, 32, 32), depth)
        shared = net.head_logits(enc, poses)
        copies = net(depth.expand(5, -1, -1, -1).contiguous(), poses)
        grid = net.jaw_grid_points(poses)
        fmap = net.encoding_cells(enc).reshape(1, 16, 16, 64).permute(0, 3, 1, 2).expand(5, -1, -1, -1)
        f = torch.nn.functional.grid_sample(fmap, grid, align_corners=False, padding_mode="border").reshape(5, -1)
        d = torch.nn.functional.grid_sample(
            depth.expand(5, -1, -1, -1), grid, align_corners=False, padding_mode="border"
        )
        want = net.roi_fc2(
            torch.relu(net.roi_fc1(torch.cat([f, (d.reshape(5, -1) - poses[:, 2:3]) / JAW_DEPTH_SCALE], 1)))
        )
        got = net.roi_term(net.encoding_cells(enc), poses, net.encoding_crop(enc))
    torch.testing.assert_close(shared, copies, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)


def test_jaw_grid_head_needs_its_feature_map_and_fast_vgqcnn():
    net = _jaw_net()
    with pytest.raises(ValueError, match="width"):
        net.head_logits(torch.zeros(1, 1024), torch.zeros(1, 7) + 0.5)  # an image term without its map
    with pytest.raises(ValueError, match="fast_vgqcnn"):
        GraspQualityNet("vgqcnn", roi_head="jaw")
    with pytest.raises(ValueError, match="roi_head"):
        GraspQualityNet("fast_vgqcnn", roi_head="ring")
