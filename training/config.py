"""Training configuration: the one place where training hyper-parameters are defined.

Defaults follow the authors' configuration (SPEC section 6): SGD with momentum 0.9, base
learning rate 0.001 decayed (staircase) by 0.95 every 4 M samples, L2 weight decay 5e-4,
two-class cross-entropy, batch 64. Counts are in *samples* (grasps), not steps, so the
schedule does not depend on the batch size or the number of processes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from vgq.crop import CONTEXT_SCALES
from vgq.normalization import IMAGE_REFERENCES
from vgq.pose import POSE_COLUMNS, POSE_FEATURES

CLASS_BALANCE = ("none", "loss_weights")
SAMPLING = ("uniform", "family")
OPTIMIZERS = ("sgd", "adamw")
PRECISIONS = ("fp32", "bf16", "auto")
SELECT_ON = ("data", "mix", "mean")
TARGETS = ("label", "success_rate", "teacher")
ROI_HEADS = ("none", "jaw", "jaw_depth")  # training.networks.GraspQualityNet's roi_head
PLACEMENTS = ("none", "image")  # training.networks.GraspQualityNet's placement off / on
ROI_UNITS = 128  # the jaw grid's hidden layer (roi_fc1's outputs): the default of roi_units


@dataclass
class TrainConfig:
    arch: str = field(default="fast_vgqcnn", metadata={"choices": tuple(POSE_COLUMNS)})
    conv2_channels: int = field(
        default=64,
        metadata={"help": "channels of the second conv stage (conv2_1, conv2_2; 16 x 16); the paper's 64"},
    )
    depth_reference: str = field(
        default="none",
        metadata={
            "choices": IMAGE_REFERENCES,
            "help": "'none': the encoder sees absolute depth (the paper's) | 'centre': each crop relative to "
            "its central depth, which enters the image term as one more input",
        },
    )
    pose_features: str = field(
        default="raw",
        metadata={
            "choices": POSE_FEATURES,
            "help": "what the pose stream reads: 'raw' (u, v, z, quaternion: the paper's) | 'rotation' "
            "(u, v, z and the grasp's rotation matrix, computed from the quaternion in the head)",
        },
    )
    pose_units: int = field(default=16, metadata={"help": "width of the pose stream pc1 (the paper's 16)"})
    roi_head: str = field(
        default="none",
        metadata={
            "choices": ROI_HEADS,
            "help": "'none': the head reads the window's image term only (the paper's) | 'jaw': it also reads "
            "the encoder's 16 x 16 feature map on a grid turned to the grasp's jaw axis (fast_vgqcnn)",
        },
    )
    roi_units: int = field(
        default=ROI_UNITS,
        metadata={"help": "width of the jaw grid's hidden layer (roi_fc1; roi_head jaw or jaw_depth)"},
    )
    placement: str = field(
        default="none",
        metadata={
            "choices": PLACEMENTS,
            "help": "'none': the head reads the window and the pose (the paper's) | 'image': also each grasp's "
            "placement on its whole object (vgq.placement; crops cut since placement rows), pc1's last inputs",
        },
    )
    placement_units: int = field(
        default=0,
        metadata={
            "help": "placement 'image': 0 = pc1 reads the row after the pose features | N > 0 = a stream of its "
            "own (pose features and row -> N units -> a term added to fc4, starting at zero in a fine-tune)"
        },
    )
    placement_lr_scale: float = field(
        default=1.0,
        metadata={"help": "learning-rate multiplier for the placement stream's layers (placement_units > 0)"},
    )
    context_scale: int = field(
        default=0,
        metadata={
            "help": "0: the window alone (the paper's) | S in 2, 3, 4: also the window's context view, S windows wide (crops "
            "cut with datagen crops --context-scale S), read by a small encoder of its own on a wider grid "
            "about the grasp (needs roi_head; its term starts at zero in a fine-tune)",
        },
    )
    context_lr_scale: float = field(
        default=1.0,
        metadata={"help": "learning-rate multiplier for the context view's layers (context_scale > 0)"},
    )
    freeze_init: bool = field(
        default=False,
        metadata={
            "help": "fine-tune: train only the layers the init lacks (a new jaw grid, placement stream or context "
            "view); the init's own layers keep its weights, so what the run gains is what the new input adds"
        },
    )
    freeze_encoder: bool = field(
        default=False,
        metadata={
            "help": "fine-tune: train only the head; the encoder's layers (training.networks.ENCODER_LAYERS, fc4's "
            "image term included) keep the init's weights, and need no backward pass"
        },
    )
    placement_dropout: float = field(
        default=0.1,
        metadata={
            "help": "placement 'image': the share of training rows whose placement row is made unknown (all 0, "
            "as an image without a table gives), drawn per step, so the network scores without one too"
        },
    )
    samples: int = 10_000_000  # training samples to see in total (paper ablations: 10 M)
    batch_size: int = 64  # global batch (split evenly over DDP processes)
    optimizer: str = field(
        default="sgd",
        metadata={
            "choices": OPTIMIZERS,
            "help": "'sgd' (the paper's, with momentum) | 'adamw' (faster start on short CPU budgets)",
        },
    )
    base_lr: float = 0.001
    momentum: float = 0.9
    weight_decay: float = 5e-4  # L2 on all parameters (SGD weight_decay)
    lr_decay: float = 0.95
    decay_every_samples: int = 4_000_000
    val_every_samples: int = 500_000
    val_max_samples: int = 0  # 0: the whole validation split
    checkpoint_every_samples: int = 100_000  # last.pt at least this often (and at each validation)
    log_every_steps: int = 50  # train-loss lines in metrics.jsonl (mean over the interval)
    eval_batch_size: int = 64  # validation rows per forward pass (small batches are faster on CPUs)
    sampling: str = field(
        default="uniform",
        metadata={
            "choices": SAMPLING,
            "help": "'uniform': each epoch is a permutation of the train split | 'family': its rows are drawn "
            "(with replacement, seeded per epoch) so that every (object family, label) cell of the train split is "
            "equally likely: a family of 4%% of the rows (bottles) weighs as much as one of 58%% (random_urdfs), "
            "and each family's classes weigh alike, as its balanced accuracy counts them; the batches then hold "
            "both classes equally, so --class-balance loss_weights is not needed",
        },
    )
    class_balance: str = field(
        default="none",
        metadata={"choices": CLASS_BALANCE, "help": "'loss_weights': cross-entropy weights n / (2 n_class) from train"},
    )
    target: str = field(
        default="label",
        metadata={
            "choices": TARGETS,
            "help": "what the loss fits: 'label' (the binary label) | 'success_rate' (the fraction of the "
            "physics label's trials that held, as a soft two-class target; physics-label crops only) | "
            "'teacher' (distillation: --teacher-weight of the loss fits a trained teacher's scores of the same "
            "rows, --teacher; the rest the label)",
        },
    )
    teacher: str = field(
        default="",
        metadata={
            "help": "target 'teacher': a folder of teacher scores of the training rows (`python -m training "
            "teacher-scores`); rows it has not scored fit the label alone"
        },
    )
    teacher_weight: float = field(
        default=0.7,
        metadata={
            "help": "target 'teacher': the share of the loss that fits the teacher's posterior as a soft "
            "two-class target; the rest fits the label (both with --class-balance's weights)"
        },
    )
    mirror: float = field(
        default=0.0,
        metadata={
            "help": "augmentation: the share of training rows shown as their left-right mirror image (crop "
            "flipped, pose by vgq.pose.mirror_poses; the label kept), drawn per step; 0 = off"
        },
    )
    seed: int = 0
    num_threads: int = 0  # torch intra-op threads per process; 0: torch default
    precision: str = field(
        default="fp32",
        metadata={
            "choices": PRECISIONS,
            "help": "training arithmetic: 'fp32' | 'bf16' (autocast; weights, optimizer and evaluation stay "
            "fp32) | 'auto' (bf16 where the CPU has native bf16 instructions, else fp32)",
        },
    )

    init: str = field(
        default="",
        metadata={
            "help": "fine-tune: a fresh run starts from this checkpoint's weights and input normalisation "
            "(a checkpoint file, a run folder: its best.pt, or an exported model folder such as "
            "models/fast-vgqcnn-default); with another --pose-features / --pose-units the pose stream starts "
            "fresh; '' = random weights"
        },
    )
    mix_data: str = field(
        default="",
        metadata={"help": "a second crop dataset whose train split supplies --mix-share of every batch"},
    )
    mix_share: float = field(
        default=0.0, metadata={"help": "share of each batch drawn at random from --mix-data's train split"}
    )
    select_on: str = field(
        default="data",
        metadata={
            "choices": SELECT_ON,
            "help": "best checkpoint by the validation balanced accuracy of 'data' (--data), 'mix' (--mix-data) "
            "or their 'mean'",
        },
    )

    def __post_init__(self) -> None:
        if self.arch not in POSE_COLUMNS:
            raise ValueError(f"unknown architecture {self.arch!r}; expected one of {sorted(POSE_COLUMNS)}")
        for name in (
            "samples",
            "batch_size",
            "decay_every_samples",
            "val_every_samples",
            "checkpoint_every_samples",
            "log_every_steps",
            "eval_batch_size",
            "conv2_channels",
            "pose_units",
            "roi_units",
        ):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.mirror <= 1.0:
            raise ValueError(f"mirror must be in [0, 1], got {self.mirror}")
        if self.placement_units < 0 or (self.placement_units and self.placement != "image"):
            raise ValueError(f"placement_units must be 0, or > 0 with placement 'image', got {self.placement_units}")
        if not self.placement_lr_scale > 0:
            raise ValueError(f"placement_lr_scale must be > 0, got {self.placement_lr_scale}")
        if not self.context_lr_scale > 0:
            raise ValueError(f"context_lr_scale must be > 0, got {self.context_lr_scale}")
        if self.context_scale not in CONTEXT_SCALES or (self.context_scale and self.roi_head == "none"):
            raise ValueError(
                f"context_scale must be one of {CONTEXT_SCALES} (> 0 with a roi_head), got {self.context_scale}"
            )
        if (self.freeze_init or self.freeze_encoder) and not self.init:
            raise ValueError("freeze_init and freeze_encoder need init (the checkpoint whose layers stay as they are)")
        if not 0.0 <= self.placement_dropout <= 1.0:
            raise ValueError(f"placement_dropout must be in [0, 1], got {self.placement_dropout}")
        if self.val_max_samples < 0 or self.num_threads < 0:
            raise ValueError("val_max_samples and num_threads must be >= 0")
        if not (self.base_lr > 0 and 0 < self.lr_decay <= 1 and 0 <= self.momentum < 1 and self.weight_decay >= 0):
            raise ValueError("need base_lr > 0, 0 < lr_decay <= 1, 0 <= momentum < 1, weight_decay >= 0")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.sampling not in SAMPLING:
            raise ValueError(f"sampling must be one of {SAMPLING}, got {self.sampling!r}")
        if self.class_balance not in CLASS_BALANCE:
            raise ValueError(f"class_balance must be one of {CLASS_BALANCE}, got {self.class_balance!r}")
        if self.roi_head not in ROI_HEADS:
            raise ValueError(f"roi_head must be one of {ROI_HEADS}, got {self.roi_head!r}")
        if self.roi_head != "none" and self.arch != "fast_vgqcnn":
            raise ValueError(f"roi_head {self.roi_head!r} needs arch fast_vgqcnn, got {self.arch!r}")
        if self.depth_reference not in IMAGE_REFERENCES:
            raise ValueError(f"depth_reference must be one of {IMAGE_REFERENCES}, got {self.depth_reference!r}")
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {self.target!r}")
        if (self.target == "teacher") != bool(self.teacher):
            raise ValueError("target 'teacher' and teacher (a folder of teacher scores) go together")
        if not 0.0 < self.teacher_weight <= 1.0:
            raise ValueError(f"teacher_weight must be in (0, 1], got {self.teacher_weight}")
        if self.teacher and self.mix_data:
            raise ValueError("target 'teacher' cannot mix a second dataset (mix_data): its rows have no teacher scores")
        if self.select_on not in SELECT_ON:
            raise ValueError(f"select_on must be one of {SELECT_ON}, got {self.select_on!r}")
        if self.mix_data and not 0.0 < self.mix_share < 1.0:
            raise ValueError(f"mix_share must be in (0, 1) with mix_data, got {self.mix_share}")
        if not self.mix_data and (self.mix_share or self.select_on != "data"):
            raise ValueError("mix_share and select_on 'mix' / 'mean' need mix_data (a second crop dataset)")

    def mix_rows(self, batch: int) -> int:
        """Rows of a (per-process) batch of ``batch`` drawn from ``mix_data``: 0 without it, else the
        share rounded, at least 1 and leaving at least 1 row of ``data``."""
        if not self.mix_data:
            return 0
        if batch < 2:
            raise ValueError(f"a batch of {batch} row cannot be shared between two datasets")
        return min(max(int(round(batch * self.mix_share)), 1), batch - 1)

    def lr_at(self, samples_seen: int) -> float:
        """Learning rate after ``samples_seen`` samples (staircase exponential decay)."""
        return self.base_lr * self.lr_decay ** (int(samples_seen) // int(self.decay_every_samples))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def defaults(cls) -> dict:
        """Every field's default: the value a config saved before the field existed had."""
        return cls().to_dict()

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown training config keys {sorted(unknown)}")
        return cls(**d)
