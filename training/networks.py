"""The networks of the paper (SPEC section 4), in torch.

One module, ``GraspQualityNet``, covers the three architectures; they differ only in the
pose columns (``vgq.pose.POSE_COLUMNS``) and in fc5 (absent in GQ-CNN):

    image stream: conv1_1 7x7/64, conv1_2 5x5/64, LRN, pool 2 | conv2_1 3x3/64,
                  conv2_2 3x3/64, LRN, pool 2 | fc3 1024
    pose stream:  pc1 16
    merge:        fc4 1024 = ReLU(W_img fc3 + W_pose pc1 + b) [-> fc5 1024] -> fc6 2

The split Fast-VGQ-CNN needs is available for every architecture:
``encode(depth) = W_img fc3`` (once per image) and ``head_logits(image_term, poses)``.
Inputs are raw (metres, crop pixels); normalisation is done inside from buffers set by
``set_normalization``, so exported graphs carry it too.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vgq.normalization import Normalization
from vgq.pose import POSE_COLUMNS

ARCHITECTURES = tuple(POSE_COLUMNS)


class LocalResponseNorm(nn.Module):
    """TensorFlow-semantics LRN: ``x / (bias + alpha * sum_{|c'-c| <= r} x_c'^2) ** beta``.

    alpha is per element (TF), not divided by the window size (torch's LocalResponseNorm).
    The channel-window sum is a 1x1 convolution with a fixed band matrix, which exports to
    ONNX as Conv + Pow and avoids onnxruntime's slow LRN kernel.
    """

    def __init__(self, channels: int, radius: int = 2, alpha: float = 2e-5, beta: float = 0.75, bias: float = 1.0):
        super().__init__()
        idx = torch.arange(channels)
        band = ((idx[:, None] - idx[None, :]).abs() <= radius).float()
        self.register_buffer("band", band[:, :, None, None], persistent=False)
        self.alpha, self.beta, self.bias = alpha, beta, bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = F.conv2d(x * x, self.band)
        return x * torch.pow(self.bias + self.alpha * s, -self.beta)


class GraspQualityNet(nn.Module):
    """VGQ-CNN / Fast-VGQ-CNN / GQ-CNN. ``forward`` returns logits (k, 2)."""

    def __init__(self, arch: str = "fast_vgqcnn", image_size: int = 32, conv2_channels: int = 64):
        super().__init__()
        if conv2_channels < 1:
            raise ValueError(f"conv2_channels must be >= 1, got {conv2_channels}")
        if arch not in POSE_COLUMNS:
            raise ValueError(f"unknown architecture {arch!r}; expected one of {ARCHITECTURES}")
        if image_size % 4:
            raise ValueError(f"image_size must be a multiple of 4, got {image_size}")
        self.arch = arch
        self.image_size = image_size
        self.pose_columns = POSE_COLUMNS[arch]
        n_pose = len(self.pose_columns)
        self.conv1_1 = nn.Conv2d(1, 64, 7, padding=3)
        self.conv1_2 = nn.Conv2d(64, 64, 5, padding=2)
        self.conv2_channels = c2 = int(conv2_channels)
        self.conv2_1 = nn.Conv2d(64, c2, 3, padding=1)
        self.conv2_2 = nn.Conv2d(c2, c2, 3, padding=1)
        self.lrn = LocalResponseNorm(64)
        self.lrn2 = LocalResponseNorm(c2)  # no weights; its own module so that export swaps both
        self.fc3 = nn.Linear(c2 * (image_size // 4) ** 2, 1024)
        self.pc1 = nn.Linear(n_pose, 16)
        self.fc4_image = nn.Linear(1024, 1024, bias=False)
        self.fc4_pose = nn.Linear(16, 1024, bias=True)  # carries fc4's bias
        self.fc5 = nn.Linear(1024, 1024) if arch != "gqcnn" else None
        self.fc6 = nn.Linear(1024, 2)
        self.register_buffer("image_mean", torch.zeros(()))
        self.register_buffer("image_std", torch.ones(()))
        self.register_buffer("pose_mean", torch.zeros(n_pose))
        self.register_buffer("pose_std", torch.ones(n_pose))

    def set_normalization(self, norm: Normalization) -> None:
        if tuple(norm.pose_columns) != tuple(self.pose_columns):
            raise ValueError(f"normalisation is for pose columns {norm.pose_columns}, net uses {self.pose_columns}")
        self.image_mean.fill_(norm.image_mean)
        self.image_std.fill_(norm.image_std)
        self.pose_mean.copy_(torch.tensor(norm.pose_mean))
        self.pose_std.copy_(torch.tensor(norm.pose_std))

    def normalization(self) -> Normalization:
        return Normalization(
            image_mean=float(self.image_mean),
            image_std=float(self.image_std),
            pose_columns=self.pose_columns,
            pose_mean=self.pose_mean.tolist(),
            pose_std=self.pose_std.tolist(),
        )

    def encode(self, depth: torch.Tensor) -> torch.Tensor:
        """Raw depth crops (n, 1, S, S) in metres -> image term of fc4 (n, 1024)."""
        x = (depth - self.image_mean) / self.image_std
        x = F.relu(self.conv1_1(x))
        x = self.lrn(F.relu(self.conv1_2(x)))
        x = F.max_pool2d(x, 2)
        x = F.relu(self.conv2_1(x))
        x = self.lrn2(F.relu(self.conv2_2(x)))
        x = F.max_pool2d(x, 2)
        x = F.relu(self.fc3(torch.flatten(x, 1)))
        return self.fc4_image(x)

    def head_logits(self, image_term: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Image term (1 or k, 1024) and raw poses (k, n_pose) -> logits (k, 2)."""
        p = F.relu(self.pc1((poses - self.pose_mean) / self.pose_std))
        x = F.relu(image_term + self.fc4_pose(p))
        if self.fc5 is not None:
            x = F.relu(self.fc5(x))
        return self.fc6(x)

    def head(self, image_term: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Success probabilities (k,) for k poses against one image term."""
        return torch.softmax(self.head_logits(image_term, poses), dim=1)[:, 1]

    def forward(self, depth: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """One crop per grasp: (k, 1, S, S) metres and (k, n_pose) raw poses -> logits (k, 2)."""
        return self.head_logits(self.encode(depth), poses)


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
