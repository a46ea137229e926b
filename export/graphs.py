"""The torch modules that are traced into ONNX graphs.

They compute exactly what ``training.networks.GraspQualityNet`` computes, arranged so
onnxruntime runs them fast:

* LRN (a band-matrix Conv + Pow in the network; no ONNX LRN node) is exported as
  ``ExportLRN``: alpha and bias folded into the band Conv, and ``d ** -0.75`` as
  ``1 / sqrt(d sqrt(d))`` (onnxruntime's general Pow is far slower than two Sqrt);
* the image term and fc4's bias enter the pose Gemm as its C input (Gemm + Relu fuse);
* the pose normalisation is folded into pc1 (``W' = W / std``, ``b' = b - W' mean``), and a
  placement row's scale (``vgq.placement``) into its columns;
* softmax(fc6)[:, 1] becomes ``sigmoid((w1 - w0) x + b1 - b0)``: one dot product per
  grasp instead of a 2-wide Gemm, a Softmax and a Gather.
* a jaw-grid head's bilinear reads are four row Gathers and a weighted sum, point-major, with
  roi_fc1's weight columns permuted to match (``_point_major_roi_fc1``): no batched (1 x 4) @ (4 x C)
  MatMul and no Transpose before roi_fc1; with a placement stream, place_fc2's columns join
  roi_fc2's (one product, int8 in the int8 head, for both terms of fc4).

Inputs are raw (metres, crop pixels); outputs are success probabilities.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from training.networks import JAW_DEPTH_SCALE, GraspQualityNet, LocalResponseNorm, rotation_entries


class ExportLRN(nn.Module):
    """``training.networks.LocalResponseNorm`` rearranged for onnxruntime, same values:
    ``d = Conv(x * x, alpha * band) + bias`` (one Conv with bias), then ``x / d ** beta``
    with ``d ** 0.75 = sqrt(d * sqrt(d))`` (exp(beta log d) for other beta). On one core of
    the reference machine this takes ~0.4 ms off a 32 x 32 encoder (Pow: 0.39 ms -> Sqrt x2:
    0.06 ms for the first LRN)."""

    def __init__(self, lrn: LocalResponseNorm):
        super().__init__()
        c = lrn.band.shape[0]
        self.register_buffer("weight", lrn.band * lrn.alpha, persistent=False)
        self.register_buffer("bias", torch.full((c,), float(lrn.bias)), persistent=False)
        self.beta = float(lrn.beta)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        d = F.conv2d(x * x, self.weight, self.bias)
        if self.beta == 0.75:
            return x / torch.sqrt(d * torch.sqrt(d))
        return x * torch.exp(-self.beta * torch.log(d))


def with_export_lrn(net: GraspQualityNet) -> GraspQualityNet:
    """A copy of ``net`` whose LocalResponseNorm modules are ExportLRN (``net`` is unchanged)."""
    net = copy.deepcopy(net)
    for name, mod in list(net.named_modules()):
        if isinstance(mod, LocalResponseNorm):
            parent = net.get_submodule(name.rpartition(".")[0]) if "." in name else net
            setattr(parent, name.rpartition(".")[2], ExportLRN(mod))
    return net


def _folded(net: GraspQualityNet, layer: nn.Linear, place: bool) -> nn.Linear:
    """``layer`` (reading the normalised pose features, then with ``place`` the row over its scale)
    as a layer of the raw columns: W' = W / std, b' = b - W' mean (and W' = W / scale for the row)."""
    n = net.n_other
    w = layer.weight.clone()
    w[:, :n] = w[:, :n] / net.pose_std[None, :n]
    if place:
        w[:, -net.n_place :] = w[:, -net.n_place :] / net.place_scale[None, :]
    out = nn.Linear(w.shape[1], w.shape[0])
    out.weight.copy_(w)
    out.bias.copy_(layer.bias - w[:, :n] @ net.pose_mean[:n])
    return out


def bilinear_point_major(rows: torch.Tensor, side: int, grid: torch.Tensor) -> torch.Tensor:
    """``GraspQualityNet._bilinear_rows`` (``bilinear_corners``: bilinear, border, align_corners
    False) as four row Gathers and a weighted sum, flattened point-major: rows of channels (n, side
    * side, C), n = 1 or k, at grid_sample coordinates (k, Ga, Gb, 2) -> (k, Ga * Gb * C), point by
    point. onnxruntime runs the four Gathers, Muls and Adds ~1.3x faster than one Gather and a
    batched tiny MatMul."""
    n, hw, c = rows.shape
    (i00, i01, i10, i11), (w00, w01, w10, w11) = GraspQualityNet.bilinear_corners(side, grid, n)
    flat = rows.reshape(n * hw, c)
    out = flat[i00] * w00[..., None] + flat[i01] * w01[..., None]
    out = out + flat[i10] * w10[..., None] + flat[i11] * w11[..., None]
    return out.reshape(grid.shape[0], -1)


def roi_fc1_point_major_columns(net: GraspQualityNet) -> np.ndarray:
    """The order of ``net.roi_fc1``'s input columns in the head graph: the graph reads the jaw grid
    point-major (``bilinear_point_major``: point p, channel ch at p * C + ch), the network
    channel-major (ch * P + p); "jaw_depth": the grid's depths stay last. Graph column j is the
    network's column ``order[j]`` (``export.from_onnx`` inverts it)."""
    c, points = net.conv2_channels, net.jaw_grid.shape[0] * net.jaw_grid.shape[1]
    cells = np.arange(c * points).reshape(c, points).T.reshape(-1)
    return np.concatenate([cells, np.arange(c * points, net.roi_fc1.in_features)])


def _point_major_roi_fc1(net: GraspQualityNet) -> nn.Linear:
    """``net.roi_fc1`` with its weight columns in the graph's point-major order (the same function)."""
    out = nn.Linear(net.roi_fc1.in_features, net.roi_fc1.out_features)
    out.weight.copy_(net.roi_fc1.weight[:, torch.from_numpy(roi_fc1_point_major_columns(net))])
    out.bias.copy_(net.roi_fc1.bias)
    return out


class _FoldedHead(nn.Module):
    """pc1 (with pose normalisation folded in) -> fc4 merge -> [fc5] -> P(success); a placement
    stream (``placement_units``) with the same folding in its first layer, its term added to fc4's."""

    def __init__(self, net: GraspQualityNet):
        super().__init__()
        self.n_other = net.n_other  # the columns normalised; "rotation": the quaternion follows them
        self.n_pose, self.n_place = net.n_pose, net.n_place  # placement: its row follows the pose columns
        self.rotation = net.pose_features == "rotation"
        with torch.no_grad():
            self.stream = bool(net.placement_units)  # the placement row read by a stream of its own
            self.pc1 = _folded(net, net.pc1, place=bool(net.n_place) and not self.stream)
            self.fc4_pose = net.fc4_pose
            self.fc5 = net.fc5  # (before ``roi``: the graph names shared weights by their first path)
            self.roi = net if net.roi_head != "none" else None  # the encoding's layout, the grid
            if self.stream:  # place_fc1 reads pc1's features and the row: folded the same way
                self.place_fc1 = _folded(net, net.place_fc1, place=True)
            if self.roi is not None:  # roi_term's layers, roi_fc1 reading the grid point-major
                self.roi_fc1, self.roi_fc2 = _point_major_roi_fc1(net), net.roi_fc2
                if self.stream:  # one product for both terms: roi_fc2 reads place_fc1's units after its own
                    self.roi_fc2 = nn.Linear(net.roi_fc2.in_features + net.placement_units, 1024, bias=False)
                    self.roi_fc2.weight.copy_(torch.cat([net.roi_fc2.weight, net.place_fc2.weight], dim=1))
            elif self.stream:
                self.place_fc2 = net.place_fc2
            self.out = nn.Linear(1024, 1)
            self.out.weight.copy_((net.fc6.weight[1] - net.fc6.weight[0])[None, :])
            self.out.bias.copy_((net.fc6.bias[1] - net.fc6.bias[0]).reshape(1))

    def _grid_units(self, image_term: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """``GraspQualityNet.roi_term`` up to roi_fc2: roi_fc1's units (k, roi_units), the feature
        map the encoding carries after its image term read point-major."""
        grid = self.roi.jaw_grid_points(poses)  # (k, Ga, Gb, 2)
        f = bilinear_point_major(self.roi.encoding_cells(image_term), self.roi.image_size // 2, grid)
        crop = self.roi.encoding_crop(image_term)
        if crop is not None:  # "jaw_depth": the crop read at the same points, relative to the grasp's z
            d = bilinear_point_major(crop, self.roi.image_size, grid)  # (k, Ga * Gb)
            f = torch.cat([f, (d - poses[:, 2:3]) / JAW_DEPTH_SCALE], dim=1)
        return F.relu(self.roi_fc1(f))

    def forward(self, image_term: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        place = poses[:, self.n_pose :] if self.n_place else None
        poses = poses[:, : self.n_pose] if self.n_place else poses
        units = None if self.roi is None else self._grid_units(image_term, poses)
        c = (image_term if units is None else image_term[:, :1024]) + self.fc4_pose.bias  # the image term first
        if self.rotation:
            poses = torch.cat([poses[:, : self.n_other], rotation_entries(poses[:, self.n_other :])], dim=1)
        if place is not None and self.stream:
            h = F.relu(self.place_fc1(torch.cat([poses, place], dim=1)))
            if units is None:
                c = c + self.place_fc2(h)
            else:  # roi_fc2 holds place_fc2's columns after its own
                units = torch.cat([units, h], dim=1)
        elif place is not None:
            poses = torch.cat([poses, place], dim=1)
        if units is not None:
            c = c + self.roi_fc2(units)
        # Gemm(p, W, C = image term + bias): the merge Add and Relu fuse into the Gemm
        x = F.relu(torch.addmm(c, F.relu(self.pc1(poses)), self.fc4_pose.weight.t()))
        if self.fc5 is not None:
            x = F.relu(self.fc5(x))
        return torch.sigmoid(self.out(x)).reshape(-1)


class EncoderGraph(nn.Module):
    """(n, 1, S, S) raw depth crops in metres -> (n, 1024) image term of fc4."""

    def __init__(self, net: GraspQualityNet):
        super().__init__()
        self.net = with_export_lrn(net)

    def forward(self, depth_crop: torch.Tensor) -> torch.Tensor:
        return self.net.encode(depth_crop)


class HeadGraph(nn.Module):
    """(1 or k, 1024) image term + (k, n_pose) raw poses -> (k,) P(success)."""

    def __init__(self, net: GraspQualityNet):
        super().__init__()
        self.head = _FoldedHead(net)

    def forward(self, image_term: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        return self.head(image_term, poses)


class OnePieceGraph(nn.Module):
    """VGQ-CNN / GQ-CNN: (k, 1, S, S) crops + (k, n_pose) raw poses -> (k,) P(success)."""

    def __init__(self, net: GraspQualityNet):
        super().__init__()
        self.net = with_export_lrn(net)
        self.head = _FoldedHead(net)

    def forward(self, depth_crops: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        return self.head(self.net.encode(depth_crops), poses)
