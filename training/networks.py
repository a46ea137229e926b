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

``depth_reference`` "centre" (``vgq.normalization``): the encoder sees each crop relative to its
own central depth and adds a learnt linear term of that depth (``fc4_ref``) to its output, so
the head and the encoder / head split are unchanged. ``pose_features`` "rotation": the pose
stream reads the grasp's rotation matrix (9 entries, from the quaternion) in place of the 4
quaternion components, ``pose_units`` wide (the paper's pc1: 16). ``placement``: the head's pose
rows carry, after the pose columns, the grasp's placement row (``vgq.placement``: where it sits on
its whole object), which pc1 reads divided by ``PLACEMENT_SCALE_M`` after the pose features; with
``placement_units`` > 0 a stream of its own reads it instead (the pose features and the scaled row
-> ``placement_units`` -> a term added to fc4, as the jaw grid's is), and pc1 stays the paper's.
``context_scale`` S > 0 (with the jaw grid): the input holds a second channel, the window's context
view (``vgq.crop.context_crops``: the same centre seen S times wider); a small encoder of its own
(two convolutions) maps it to a 16 x 16 feature map that the head reads on a wider grid around the
grasp, turned to its jaw as the jaw grid is (``CONTEXT_GRID``, metres), into a term added to fc4 (its
last layer zero at the start of a fine-tune): what the window cannot show, where the grasp sits on
an object larger than it. The view is read as depth about its own mean (its shape, not the camera's
distance).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from training.config import ROI_HEADS, ROI_UNITS
from vgq.crop import CONTEXT_SCALES
from vgq.normalization import IMAGE_REFERENCES, REFERENCE_PIXELS, Normalization
from vgq.placement import PLACEMENT_COLUMNS, PLACEMENT_SCALE_M
from vgq.pose import POSE_COLUMNS, POSE_FEATURES

ARCHITECTURES = tuple(POSE_COLUMNS)
# the jaw grid (metres in the gripper's frame, at the grasp's depth): along the jaw axis, across it
JAW_GRID_ALONG = (-0.04, 0.04, 8)
JAW_GRID_ACROSS = (-0.012, 0.012, 3)
CONTEXT_GRID = (-0.12, 0.12, 5)  # the context grid, along and across the jaw (metres at the grasp's depth)
CONTEXT_CHANNELS = (32, 64)  # the context encoder's two convolutions
JAW_DEPTH_SCALE = 0.01  # metres: "jaw_depth" reads the depth at each grid point relative to the grasp's, in cm


def rotation_entries(q: torch.Tensor) -> torch.Tensor:
    """(k, 9) row-major rotation matrices of (k, 4) unit quaternions (w, x, y, z): torch's
    ``vgq.pose.pose_stream_features`` "rotation" (a test holds the two equal)."""
    w, x, y, z = q.unbind(1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=1,
    )  # fmt: skip


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


#: the layers ``GraspQualityNet.encode`` runs (the exported encoder graph's): fc4's image term
#: included; the context view's convolutions too (its grid read and layers are the head's)
ENCODER_LAYERS = ("conv1_1", "conv1_2", "conv2_1", "conv2_2", "fc3", "fc4_image", "fc4_ref", "ctx_conv1", "ctx_conv2")


class GraspQualityNet(nn.Module):
    """VGQ-CNN / Fast-VGQ-CNN / GQ-CNN. ``forward`` returns logits (k, 2)."""

    def __init__(
        self,
        arch: str = "fast_vgqcnn",
        image_size: int = 32,
        conv2_channels: int = 64,
        depth_reference: str = "none",
        pose_features: str = "raw",
        pose_units: int = 16,
        roi_head: str = "none",
        roi_focal_px: float = 175.0,
        roi_units: int = ROI_UNITS,
        placement: bool = False,
        placement_units: int = 0,
        context_scale: int = 0,
    ):
        super().__init__()
        if roi_head not in ROI_HEADS:
            raise ValueError(f"roi_head must be one of {ROI_HEADS}, got {roi_head!r}")
        if roi_head != "none" and arch != "fast_vgqcnn":
            raise ValueError(f"roi_head {roi_head!r} reads (u, v) offsets: it needs fast_vgqcnn, got {arch!r}")
        if not roi_focal_px > 0:
            raise ValueError(f"roi_focal_px must be > 0, got {roi_focal_px}")
        if pose_features not in POSE_FEATURES:
            raise ValueError(f"pose_features must be one of {POSE_FEATURES}, got {pose_features!r}")
        if pose_units < 1:
            raise ValueError(f"pose_units must be >= 1, got {pose_units}")
        if roi_units < 1:
            raise ValueError(f"roi_units must be >= 1, got {roi_units}")
        if placement_units < 0 or (placement_units and not placement):
            raise ValueError(f"placement_units must be 0, or > 0 with placement, got {placement_units}")
        if context_scale not in CONTEXT_SCALES or (context_scale and roi_head == "none"):
            raise ValueError(
                f"context_scale must be one of {CONTEXT_SCALES} (> 0 with a jaw grid), got {context_scale}"
            )
        if depth_reference not in IMAGE_REFERENCES:
            raise ValueError(f"depth_reference must be one of {IMAGE_REFERENCES}, got {depth_reference!r}")
        self.depth_reference = depth_reference
        if conv2_channels < 1:
            raise ValueError(f"conv2_channels must be >= 1, got {conv2_channels}")
        if arch not in POSE_COLUMNS:
            raise ValueError(f"unknown architecture {arch!r}; expected one of {ARCHITECTURES}")
        if image_size % 4:
            raise ValueError(f"image_size must be a multiple of 4, got {image_size}")
        self.arch = arch
        self.image_size = image_size
        self.pose_columns = POSE_COLUMNS[arch]
        self.n_pose = n_pose = len(self.pose_columns)
        self.n_place = len(PLACEMENT_COLUMNS) if placement else 0
        self.conv1_1 = nn.Conv2d(1, 64, 7, padding=3)
        self.conv1_2 = nn.Conv2d(64, 64, 5, padding=2)
        self.conv2_channels = c2 = int(conv2_channels)
        self.conv2_1 = nn.Conv2d(64, c2, 3, padding=1)
        self.conv2_2 = nn.Conv2d(c2, c2, 3, padding=1)
        self.lrn = LocalResponseNorm(64)
        self.lrn2 = LocalResponseNorm(c2)  # no weights; its own module so that export swaps both
        self.fc3 = nn.Linear(c2 * (image_size // 4) ** 2, 1024)
        if pose_features == "rotation" and tuple(self.pose_columns[-4:]) != ("qw", "qx", "qy", "qz"):
            raise ValueError(f"pose_features 'rotation' needs quaternion columns; {arch} has {self.pose_columns}")
        self.pose_features, self.pose_units = pose_features, int(pose_units)
        self.n_other = n_pose - 4 if pose_features == "rotation" else n_pose  # columns read as they are
        n_feat = n_pose if pose_features == "raw" else self.n_other + 9  # pc1's pose features
        self.placement_units = int(placement_units)
        self.pc1 = nn.Linear(n_feat + (0 if self.placement_units else self.n_place), self.pose_units)
        if self.placement_units:  # the placement stream: fc4's term from the pose features and the row
            self.place_fc1 = nn.Linear(n_feat + self.n_place, self.placement_units)
            self.place_fc2 = nn.Linear(self.placement_units, 1024, bias=False)
        self.register_buffer("place_scale", torch.tensor(PLACEMENT_SCALE_M[: self.n_place]), persistent=False)
        self.fc4_image = nn.Linear(1024, 1024, bias=False)
        self.fc4_ref = nn.Linear(1, 1024, bias=False) if depth_reference != "none" else None
        self.fc4_pose = nn.Linear(self.pose_units, 1024, bias=True)  # carries fc4's bias
        self.fc5 = nn.Linear(1024, 1024) if arch != "gqcnn" else None
        self.fc6 = nn.Linear(1024, 2)
        self.roi_head = roi_head
        if roi_head != "none":
            a, b = torch.linspace(*JAW_GRID_ALONG), torch.linspace(*JAW_GRID_ACROSS)
            grid = torch.stack(torch.meshgrid(a, b, indexing="ij"), dim=-1)  # (Ga, Gb, 2) metres
            self.register_buffer("jaw_grid", grid, persistent=False)
            self.register_buffer("roi_focal_px", torch.tensor(float(roi_focal_px)))
            points = grid.shape[0] * grid.shape[1]  # "jaw_depth": then one relative depth per point
            self.roi_fc1 = nn.Linear((c2 + (roi_head == "jaw_depth")) * points, int(roi_units))
            self.roi_fc2 = nn.Linear(int(roi_units), 1024, bias=False)
        self.context_scale = int(context_scale)
        if self.context_scale:
            c1, c3 = CONTEXT_CHANNELS
            self.ctx_conv1 = nn.Conv2d(1, c1, 5, padding=2)
            self.ctx_conv2 = nn.Conv2d(c1, c3, 3, padding=1)
            g = torch.linspace(*CONTEXT_GRID)
            self.register_buffer("ctx_grid", torch.stack(torch.meshgrid(g, g, indexing="ij"), -1), persistent=False)
            self.ctx_fc1 = nn.Linear(c3 * len(g) ** 2, int(roi_units))
            self.ctx_fc2 = nn.Linear(int(roi_units), 1024, bias=False)
        self.register_buffer("image_mean", torch.zeros(()))
        self.register_buffer("image_std", torch.ones(()))
        self.register_buffer("pose_mean", torch.zeros(n_pose))
        self.register_buffer("pose_std", torch.ones(n_pose))
        self.register_buffer("reference_mean", torch.zeros(()))
        self.register_buffer("reference_std", torch.ones(()))

    def set_normalization(self, norm: Normalization) -> None:
        if tuple(norm.pose_columns) != tuple(self.pose_columns):
            raise ValueError(f"normalisation is for pose columns {norm.pose_columns}, net uses {self.pose_columns}")
        if norm.image_reference != self.depth_reference:
            raise ValueError(
                f"normalisation has image_reference {norm.image_reference!r}, net {self.depth_reference!r}"
            )
        self.reference_mean.fill_(norm.reference_mean)
        self.reference_std.fill_(norm.reference_std)
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
            image_reference=self.depth_reference,
            reference_mean=float(self.reference_mean),
            reference_std=float(self.reference_std),
        )

    @property
    def encoding_width(self) -> int:
        """Width of ``encode``'s output: fc4's image term (1024), then with ``roi_head`` the conv2
        feature map (S/2 x S/2 x C: a row of C channels per map cell) that the head's jaw grid reads,
        and with ``context_scale`` the context view's feature map last."""
        cells = self._cells_width if self.roi_head != "none" else 0
        ctx = self._context_width if self.context_scale else 0
        return 1024 + cells + (self.image_size**2 if self.roi_head == "jaw_depth" else 0) + ctx

    @property
    def _cells_width(self) -> int:
        """Floats of the conv2 feature map a jaw-grid encoding carries (S/2 * S/2 * C)."""
        return self.conv2_channels * (self.image_size // 2) ** 2

    @property
    def _context_width(self) -> int:
        """Floats of the context view's feature map a context encoding carries last (S/2 * S/2 * C)."""
        return CONTEXT_CHANNELS[1] * (self.image_size // 2) ** 2

    def encode(self, depth: torch.Tensor) -> torch.Tensor:
        """Raw depth crops (n, 1, S, S) in metres -> (n, ``encoding_width``): the image term of fc4,
        followed with ``roi_head`` by the flattened conv2 feature map (and for "jaw_depth" the raw
        crop; with ``context_scale`` the input is (n, 2, S, S), the window and its context view, and
        the context's feature map comes last). One array per window, so
        the encoder / head split (export, the service's cache) is the same for both heads."""
        if not torch.jit.is_tracing() and depth.shape[1] != 1 + bool(self.context_scale):  # (export traces this)
            raise ValueError(f"the encoder reads {1 + bool(self.context_scale)} channel(s), got {depth.shape[1]}")
        context, depth = depth[:, 1:], depth[:, :1]
        ref, raw = None, depth
        if self.fc4_ref is not None:
            lo = (depth.shape[-1] - REFERENCE_PIXELS) // 2
            ref = depth[:, :, lo : lo + REFERENCE_PIXELS, lo : lo + REFERENCE_PIXELS].mean(dim=(2, 3), keepdim=True)
            depth = depth - ref
        x = (depth - self.image_mean) / self.image_std
        x = F.relu(self.conv1_1(x))
        x = self.lrn(F.relu(self.conv1_2(x)))
        x = F.max_pool2d(x, 2)
        x = F.relu(self.conv2_1(x))
        fmap = self.lrn2(F.relu(self.conv2_2(x)))
        x = F.max_pool2d(fmap, 2)
        x = F.relu(self.fc3(torch.flatten(x, 1)))
        term = self.fc4_image(x)
        if ref is not None:
            term = term + self.fc4_ref((ref.flatten(1) - self.reference_mean) / self.reference_std)
        if self.roi_head == "none":
            return term
        parts = [term, fmap.permute(0, 2, 3, 1).reshape(fmap.shape[0], -1)]  # rows of channels
        if self.roi_head == "jaw_depth":  # and the crop itself (metres), read at the grid points
            parts.append(raw.reshape(raw.shape[0], -1))
        if self.context_scale:  # the context view's own feature map, as rows of channels
            # depth about the view's own mean: the shape around the grasp, not how far the camera stood
            # (a global offset that varies by view would swing every unit on or off together)
            c = (context - context.mean(dim=(2, 3), keepdim=True)) / self.image_std
            c = F.max_pool2d(F.relu(self.ctx_conv1(c)), 2)
            c = F.relu(self.ctx_conv2(c))
            parts.append(c.permute(0, 2, 3, 1).reshape(c.shape[0], -1))
        return torch.cat(parts, dim=1)

    def encoding_cells(self, encoding: torch.Tensor) -> torch.Tensor:
        """The feature map an encoding (n, ``encoding_width``) carries after its image term, as
        rows of channels (n, S/2 * S/2, C): what ``roi_term`` reads."""
        cells = encoding[:, 1024 : 1024 + self._cells_width]
        return cells.reshape(encoding.shape[0], -1, self.conv2_channels)

    def encoding_crop(self, encoding: torch.Tensor) -> torch.Tensor | None:
        """The raw crop (n, S * S, 1) in metres a "jaw_depth" encoding carries (else None)."""
        if self.roi_head != "jaw_depth":
            return None
        lo = 1024 + self._cells_width
        return encoding[:, lo : lo + self.image_size**2].reshape(encoding.shape[0], -1, 1)

    def encoding_context(self, encoding: torch.Tensor) -> torch.Tensor | None:
        """The context feature map (n, S/2 * S/2, C) an encoding carries last (None without context)."""
        if not self.context_scale:
            return None
        return encoding[:, -self._context_width :].reshape(encoding.shape[0], -1, CONTEXT_CHANNELS[1])

    def jaw_grid_points(self, poses: torch.Tensor, grid: torch.Tensor | None = None, scale: int = 1) -> torch.Tensor:
        """(k, Ga, Gb, 2) grid_sample coordinates (-1..1 across the crop, u then v) of each grasp's
        jaw grid (``grid`` (Ga, Gb, 2) metres along and across the jaw; default the jaw grid's), in a
        view ``scale`` times wider than the window (the context view): raw poses (u, v offsets in crop
        px, z metres, q w x y z). The in-image jaw
        direction is the projection of the rotation's x column, ignoring the perspective term of
        the grasp's distance from the optical axis; its sign is chosen with u >= 0."""
        grid = self.jaw_grid if grid is None else grid
        u, v, z = poses[:, 0], poses[:, 1], poses[:, 2]
        r = rotation_entries(poses[:, 3:7])  # row-major: the x column is entries 0, 3, 6
        du, dv = r[:, 0], r[:, 3]
        sign = torch.where(du < 0, -1.0, 1.0)
        n = torch.sqrt(du * du + dv * dv).clamp_min(1e-6)
        du, dv = du * sign / n, dv * sign / n
        u, v = u / scale, v / scale
        s = self.roi_focal_px / z.clamp_min(0.05) / scale  # crop px per metre
        a, b = grid[..., 0], grid[..., 1]  # (Ga, Gb)
        pu = u[:, None, None] + s[:, None, None] * (a * du[:, None, None] - b * dv[:, None, None])
        pv = v[:, None, None] + s[:, None, None] * (a * dv[:, None, None] + b * du[:, None, None])
        half = self.image_size / 2
        return torch.stack([pu / half, pv / half], dim=-1)

    @staticmethod
    def bilinear_corners(
        side: int, grid: torch.Tensor, n: int
    ) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
        """Bilinear reads (``F.grid_sample``'s bilinear, border, align_corners False) of a map stored
        as rows (n * side * side, C), n = 1 (one window, k grasps) or k (a window each), at grid_sample
        coordinates (k, Ga, Gb, 2): the rows of the four corners (y0 x0, y0 x1, y1 x0, y1 x1), each
        (k, Ga, Gb) int64, and their weights, each (k, Ga, Gb)."""
        k = grid.shape[0]
        xy = (((grid + 1) * side - 1) / 2).clamp(0, side - 1)  # map cells, pixel centres on integers
        lo = xy.floor()
        w = xy - lo  # (k, Ga, Gb, 2)
        x0, y0 = lo[..., 0].long(), lo[..., 1].long()
        x1, y1 = (x0 + 1).clamp(max=side - 1), (y0 + 1).clamp(max=side - 1)
        first = (torch.arange(k, device=grid.device) // (k // n) * side * side)[:, None, None]  # each grasp's window
        y0, y1 = y0 * side + first, y1 * side + first
        wx, wy = w[..., 0], w[..., 1]
        return (y0 + x0, y0 + x1, y1 + x0, y1 + x1), ((1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy)

    @staticmethod
    def _bilinear_rows(rows: torch.Tensor, side: int, grid: torch.Tensor) -> torch.Tensor:
        """Bilinear reads (``bilinear_corners``) of a map stored as rows of channels (n, side * side,
        C), n = 1 or k, at grid_sample coordinates (k, Ga, Gb, 2) -> (k, Ga, Gb, C) (a test holds them
        equal to ``F.grid_sample``'s), done as one row gather and a batched (1 x 4) @ (4 x C) MatMul:
        onnxruntime's GridSample took 4.2 ms for 128 grasps, this ~0.5 ms (export.graphs reads the
        corners with four Gathers instead, faster still)."""
        n, hw, c = rows.shape
        idx, wts = GraspQualityNet.bilinear_corners(side, grid, n)
        wts = torch.stack(wts, dim=-1)[..., None, :].to(rows.dtype)
        return (wts @ rows.reshape(n * hw, c)[torch.stack(idx, dim=-1)]).squeeze(-2)

    def roi_term(self, cells: torch.Tensor, poses: torch.Tensor, crop: torch.Tensor | None = None) -> torch.Tensor:
        """fc4's jaw-grid term (k, 1024): ``cells`` the conv2 feature map as rows of channels
        (1 or k, S/2 * S/2, C), raw poses (k, n_pose); for "jaw_depth" also the raw crop as rows
        (1 or k, S * S, 1), read at the same points as depth relative to the grasp's z (in
        JAW_DEPTH_SCALE units)."""
        grid = self.jaw_grid_points(poses)  # (k, Ga, Gb, 2)
        k, ga, gb, _ = grid.shape
        f = self._bilinear_rows(cells, self.image_size // 2, grid)  # (k, Ga, Gb, C)
        f = f.permute(0, 3, 1, 2).reshape(k, -1)  # roi_fc1 reads channel-major
        if self.roi_head == "jaw_depth":
            d = self._bilinear_rows(crop, self.image_size, grid).reshape(k, ga * gb)
            f = torch.cat([f, (d - poses[:, 2:3]) / JAW_DEPTH_SCALE], dim=1)
        return self.roi_fc2(F.relu(self.roi_fc1(f)))

    def context_term(self, cells: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """fc4's context term (k, 1024): the context feature map as rows of channels (1 or k, S/2 *
        S/2, C) read on ``CONTEXT_GRID`` about each grasp (raw poses (k, n_pose)), turned to its jaw."""
        grid = self.jaw_grid_points(poses, self.ctx_grid, self.context_scale)
        f = self._bilinear_rows(cells, self.image_size // 2, grid)
        f = f.permute(0, 3, 1, 2).reshape(grid.shape[0], -1)
        return self.ctx_fc2(F.relu(self.ctx_fc1(f)))

    def head_logits(self, encoding: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """``encode``'s output (1 or k, ``encoding_width``) and raw poses (k, n_pose) -> logits (k, 2)
        (with ``placement``: (k, n_pose + 7), the placement row after the pose columns)."""
        if encoding.shape[1] != self.encoding_width:
            raise ValueError(f"the head reads encodings of width {self.encoding_width}, got {encoding.shape[1]}")
        if poses.shape[1] != self.n_pose + self.n_place:
            raise ValueError(f"the head reads pose rows of width {self.n_pose + self.n_place}, got {poses.shape[1]}")
        place, poses = poses[:, self.n_pose :], poses[:, : self.n_pose]
        p = (poses - self.pose_mean) / self.pose_std
        if self.pose_features == "rotation":
            p = torch.cat([p[:, : self.n_other], rotation_entries(poses[:, self.n_other :])], dim=1)
        x = encoding[:, :1024]
        if self.placement_units:
            q = torch.cat([p, place / self.place_scale], dim=1)
            x = x + self.place_fc2(F.relu(self.place_fc1(q)))
        elif self.n_place:
            p = torch.cat([p, place / self.place_scale], dim=1)
        x = x + self.fc4_pose(F.relu(self.pc1(p)))
        if self.roi_head != "none":
            x = x + self.roi_term(self.encoding_cells(encoding), poses, self.encoding_crop(encoding))
        if self.context_scale:
            x = x + self.context_term(self.encoding_context(encoding), poses)
        x = F.relu(x)
        if self.fc5 is not None:
            x = F.relu(self.fc5(x))
        return self.fc6(x)

    def head(self, encoding: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Success probabilities (k,) for k poses against one window's encoding."""
        return torch.softmax(self.head_logits(encoding, poses), dim=1)[:, 1]

    def forward(self, depth: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """One crop per grasp: (k, 1, S, S) metres (with ``context_scale`` (k, 2, S, S)) and (k, n_pose) raw poses -> logits (k, 2)."""
        return self.head_logits(self.encode(depth), poses)


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
