"""Policy networks: ``bc`` (conv encoder + spatial softmax + MLP) and ``act_lite`` (small transformer).

Both map one observation (normalized proprioception, shape (B, S), and one RGB image per camera,
float in [0, 1], shape (B, 3, H, W)) to a chunk of future actions in normalized units, shape
(B, chunk, A): the next ``chunk`` actions starting at the observation's frame. Predicting chunks
rather than single actions is what made ACT (Zhao et al. 2023) and Diffusion Policy work on small
demonstration sets: the policy commits to a coherent motion instead of averaging hesitations frame
by frame, and it is queried ``chunk`` times less often.

What we took from reading robomimic's BC-RNN / LeRobot's ACT and diffusion code (not their code):

* a small conv trunk ending in a **spatial softmax** (Levine et al. 2016; robomimic's and
  Diffusion Policy's image encoder) turns a feature map into keypoint coordinates, which carry
  *where* the cube is far better than a global average pool does at low resolution;
* GroupNorm instead of BatchNorm (Diffusion Policy): batch statistics make a policy evaluated one
  sample at a time behave differently from training;
* ``act_lite`` keeps ACT's structure (a transformer encoder over the state token and the image
  feature tokens with 2D sine positions, a decoder of ``chunk`` learned queries, L1 loss) without
  the CVAE and ResNet-18 backbone that a CPU cannot train in 30 minutes.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass
from typing import Literal

import torch
import torch.nn.functional as F  # noqa: N812 (torch's convention)
from torch import nn

from telerig.errors import PolicyError

__all__ = [
    "POLICY_TYPES",
    "ActLite",
    "BcPolicy",
    "ChunkPolicy",
    "ModelConfig",
    "PolicyType",
    "build_model",
]

PolicyType = Literal["bc", "act_lite"]
#: The policy types :func:`build_model` builds.
POLICY_TYPES: tuple[PolicyType, ...] = ("bc", "act_lite")


@dataclass(frozen=True, slots=True)
class ModelConfig:
    """Shape and size of a policy network; stored in the checkpoint as JSON.

    Attributes:
        policy_type: ``bc`` or ``act_lite``.
        state_dim: Length S of the proprioceptive state vector.
        action_dim: Length A of one action.
        camera_keys: Cameras the policy sees, each through its own encoder, in this order.
        image_size: (H, W) [px] of every camera image the network takes.
        chunk_size: Actions predicted per observation.
        channels: Conv trunk widths; each stage halves the resolution (stride 2).
        keypoints: Spatial-softmax keypoints per camera (``bc``).
        hidden: MLP width (``bc``) or transformer model width (``act_lite``).
        layers: MLP hidden layers (``bc``) or encoder / decoder layers each (``act_lite``).
        heads: Attention heads (``act_lite``).
        dropout: Dropout in the MLP / transformer (0 keeps inference and training alike).
    """

    policy_type: PolicyType
    state_dim: int
    action_dim: int
    camera_keys: tuple[str, ...]
    image_size: tuple[int, int]
    chunk_size: int
    channels: tuple[int, ...] = (16, 32, 32)
    keypoints: int = 32
    hidden: int = 256
    layers: int = 2
    heads: int = 4
    dropout: float = 0.0

    def __post_init__(self) -> None:
        if self.policy_type not in POLICY_TYPES:
            raise PolicyError(
                f"unknown policy type {self.policy_type!r}; use one of {', '.join(POLICY_TYPES)}"
            )
        for name in ("state_dim", "action_dim", "chunk_size", "keypoints", "hidden", "layers", "heads"):
            if getattr(self, name) < 1:
                raise PolicyError(f"policy {name} must be >= 1, got {getattr(self, name)}")
        if len(self.image_size) != 2 or min(self.image_size) < 8:
            raise PolicyError(f"policy image size must be (H, W) >= 8 px, got {self.image_size}")
        if not self.channels:
            raise PolicyError("policy channels must name at least one conv stage")
        if self.policy_type == "act_lite" and self.hidden % self.heads:
            raise PolicyError(f"act_lite hidden ({self.hidden}) must be a multiple of heads ({self.heads})")
        if not 0.0 <= self.dropout < 1.0:
            raise PolicyError(f"policy dropout must be in [0, 1), got {self.dropout}")

    def to_json(self) -> dict[str, object]:
        """JSON-ready dict (tuples as lists)."""
        return asdict(self)

    @classmethod
    def from_json(cls, data: object) -> ModelConfig:
        """Parse :meth:`to_json` output; one-line :class:`PolicyError` on anything else."""
        if not isinstance(data, dict):
            raise PolicyError("checkpoint model config is not an object; was it written by telerig train?")
        try:
            return cls(
                policy_type=data["policy_type"],
                state_dim=int(data["state_dim"]),
                action_dim=int(data["action_dim"]),
                camera_keys=tuple(str(k) for k in data["camera_keys"]),
                image_size=(int(data["image_size"][0]), int(data["image_size"][1])),
                chunk_size=int(data["chunk_size"]),
                channels=tuple(int(c) for c in data["channels"]),
                keypoints=int(data["keypoints"]),
                hidden=int(data["hidden"]),
                layers=int(data["layers"]),
                heads=int(data["heads"]),
                dropout=float(data["dropout"]),
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise PolicyError(
                f"checkpoint model config is invalid ({exc!r}); retrain with telerig train"
            ) from None


def _groups(channels: int) -> int:
    return math.gcd(channels, 8)


class ConvTrunk(nn.Module):
    """Stride-2 conv stages with GroupNorm and ReLU: (B, 3, H, W) → (B, C, H / 2^n, W / 2^n)."""

    def __init__(self, channels: tuple[int, ...]) -> None:
        super().__init__()
        stages: list[nn.Module] = []
        width = 3
        for out in channels:
            stages += [
                nn.Conv2d(width, out, kernel_size=3, stride=2, padding=1),
                nn.GroupNorm(_groups(out), out),
                nn.ReLU(inplace=True),
                nn.Conv2d(out, out, kernel_size=3, padding=1),
                nn.GroupNorm(_groups(out), out),
                nn.ReLU(inplace=True),
            ]
            width = out
        self.net = nn.Sequential(*stages)
        self.out_channels = width

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        # [0, 1] → roughly zero-centred; fixed, so the runner needs no image statistics.
        out: torch.Tensor = self.net(image * 2.0 - 1.0)
        return out


class SpatialSoftmax(nn.Module):
    """Feature map (B, C, h, w) → K keypoints' expected (x, y) in [-1, 1], flattened to (B, 2K)."""

    def __init__(self, channels: int, keypoints: int) -> None:
        super().__init__()
        self.project = nn.Conv2d(channels, keypoints, kernel_size=1)
        self.keypoints = keypoints

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        b, _, h, w = features.shape
        logits = self.project(features).flatten(2)  # (B, K, h*w)
        attention = torch.softmax(logits, dim=-1)
        ys = torch.linspace(-1.0, 1.0, h, device=features.device)
        xs = torch.linspace(-1.0, 1.0, w, device=features.device)
        grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
        x = (attention * grid_x.reshape(1, 1, -1)).sum(-1)
        y = (attention * grid_y.reshape(1, 1, -1)).sum(-1)
        return torch.stack((x, y), dim=-1).reshape(b, 2 * self.keypoints)


def _mlp(sizes: list[int], dropout: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers += [nn.ReLU(inplace=True), nn.Dropout(dropout)] if dropout else [nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class ChunkPolicy(nn.Module):
    """Common interface: ``forward(state, images) -> (B, chunk, A)`` and ``loss(pred, target)``.

    ``state`` is normalized proprioception (B, S); ``images`` maps each of ``config.camera_keys``
    to (B, 3, H, W) float in [0, 1]; actions are normalized (zero mean, unit std per entry).
    """

    config: ModelConfig

    def forward(self, state: torch.Tensor, images: dict[str, torch.Tensor]) -> torch.Tensor:
        raise NotImplementedError

    def loss(
        self, pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Mean L1 over chunk and action entries (ACT's loss; robust to the odd bad demonstration);
        with ``weights`` (A,), the mean weighted per action entry, divided by the weights' mean (so
        weights of 1 give plain L1)."""
        if weights is None:
            return F.l1_loss(pred, target)
        return ((pred - target).abs() * weights).mean() / weights.mean()


class BcPolicy(ChunkPolicy):
    """Behaviour cloning: per-camera conv trunk + spatial softmax, concatenated with the state, MLP."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        trunk_out = config.channels[-1]
        self.trunks = nn.ModuleDict({key: ConvTrunk(config.channels) for key in config.camera_keys})
        self.pools = nn.ModuleDict(
            {key: SpatialSoftmax(trunk_out, config.keypoints) for key in config.camera_keys}
        )
        width = config.state_dim + 2 * config.keypoints * len(config.camera_keys)
        sizes = [width] + [config.hidden] * config.layers + [config.chunk_size * config.action_dim]
        self.head = _mlp(sizes, config.dropout)

    def forward(self, state: torch.Tensor, images: dict[str, torch.Tensor]) -> torch.Tensor:
        parts = [state]
        for key in self.config.camera_keys:
            parts.append(self.pools[key](self.trunks[key](images[key])))
        out: torch.Tensor = self.head(torch.cat(parts, dim=-1))
        return out.reshape(-1, self.config.chunk_size, self.config.action_dim)


def _sine_2d(h: int, w: int, dim: int) -> torch.Tensor:
    """DETR's 2D sine position embedding, (h*w, dim): half the channels for y, half for x."""
    quarter = dim // 4
    freq = torch.exp(-math.log(10000.0) * torch.arange(quarter, dtype=torch.float32) / max(quarter, 1))
    ys = torch.arange(h, dtype=torch.float32)[:, None] * freq[None, :]
    xs = torch.arange(w, dtype=torch.float32)[:, None] * freq[None, :]
    y = torch.cat((ys.sin(), ys.cos()), dim=-1)[:, None, :].expand(h, w, 2 * quarter)
    x = torch.cat((xs.sin(), xs.cos()), dim=-1)[None, :, :].expand(h, w, 2 * quarter)
    pos = torch.cat((y, x), dim=-1).reshape(h * w, 4 * quarter)
    return F.pad(pos, (0, dim - 4 * quarter))


class ActLite(ChunkPolicy):
    """ACT without the CVAE: transformer encoder over [state, image tokens], decoder of chunk queries."""

    positions: torch.Tensor  # a non-persistent buffer: (h*w, hidden) sine positions of the tokens

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        d = config.hidden
        self.trunks = nn.ModuleDict({key: ConvTrunk(config.channels) for key in config.camera_keys})
        self.project = nn.ModuleDict(
            {key: nn.Conv2d(config.channels[-1], d, kernel_size=1) for key in config.camera_keys}
        )
        self.camera_embed = nn.Parameter(torch.zeros(max(len(config.camera_keys), 1), d))
        self.state_in = nn.Linear(config.state_dim, d)
        self.state_embed = nn.Parameter(torch.zeros(1, 1, d))
        self.queries = nn.Parameter(torch.randn(config.chunk_size, d) * 0.02)
        # Pre-norm layers (ACT's and most small transformers' choice: stable without warm-up).
        self.encoder = nn.TransformerEncoder(
            nn.TransformerEncoderLayer(
                d, config.heads, 4 * d, config.dropout, batch_first=True, norm_first=True
            ),
            config.layers,
            norm=nn.LayerNorm(d),
            enable_nested_tensor=False,
        )
        self.decoder = nn.TransformerDecoder(
            nn.TransformerDecoderLayer(
                d, config.heads, 4 * d, config.dropout, batch_first=True, norm_first=True
            ),
            config.layers,
            norm=nn.LayerNorm(d),
        )
        self.action_out = nn.Linear(d, config.action_dim)
        h, w = config.image_size
        stride = 2 ** len(config.channels)
        self.register_buffer(
            "positions", _sine_2d(math.ceil(h / stride), math.ceil(w / stride), d), persistent=False
        )

    def forward(self, state: torch.Tensor, images: dict[str, torch.Tensor]) -> torch.Tensor:
        tokens = [self.state_in(state)[:, None, :] + self.state_embed]
        positions = self.positions
        for i, key in enumerate(self.config.camera_keys):
            feat = self.project[key](self.trunks[key](images[key])).flatten(2).transpose(1, 2)  # (B, hw, d)
            tokens.append(feat + positions[None, : feat.shape[1]] + self.camera_embed[i])
        memory_in = torch.cat(tokens, dim=1)
        queries = self.queries[None].expand(state.shape[0], -1, -1)
        out: torch.Tensor = self.action_out(self.decoder(queries, self.encoder(memory_in)))
        return out


def build_model(config: ModelConfig) -> ChunkPolicy:
    """The network for ``config.policy_type``, randomly initialised (torch's global RNG)."""
    if config.policy_type == "bc":
        return BcPolicy(config)
    return ActLite(config)
