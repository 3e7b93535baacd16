"""Camera frames to policy input: one resize used by training and inference alike.

The dataset reader (:mod:`telerig.learn.dataset`) resizes decoded video frames with
:func:`resize_rgb` once and caches them; the runner resizes live frames with the same function when
they are not already at the policy's size. Same function, same pixels: a policy never sees a
differently filtered image at rollout than in training.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F  # noqa: N812 (torch's convention)

from telerig.errors import PolicyError

__all__ = ["random_shift", "resize_rgb", "to_tensor"]

UInt8Image = npt.NDArray[np.uint8]
#: Largest frame side [px] accepted: an 8K frame is a bug upstream, not something to resize per tick.
MAX_SIDE = 8192


def resize_rgb(frames: UInt8Image, size: tuple[int, int]) -> UInt8Image:
    """Resize RGB frames to ``size`` = (H, W) [px]: area averaging down, bilinear up.

    Area averaging is what camera pipelines use to shrink (OpenCV ``INTER_AREA``, swscale
    ``AREA``): a 640x480 frame and swscale's 64x48 differ by 0.8 grey levels on average.

    Args:
        frames: uint8, shape (H0, W0, 3) or (N, H0, W0, 3).

    Returns:
        uint8 of shape (h, w, 3) or (N, h, w, 3); the input itself when it already has that size.

    Raises:
        PolicyError: Not uint8 RGB.
    """
    if frames.dtype != np.uint8 or frames.ndim not in (3, 4) or frames.shape[-1] != 3:
        raise PolicyError(
            f"camera frames must be uint8 RGB (H, W, 3), got {frames.dtype} of shape {frames.shape}"
        )
    h0, w0 = frames.shape[-3:-1]
    if not (0 < h0 <= MAX_SIDE and 0 < w0 <= MAX_SIDE):
        raise PolicyError(f"camera frames must be 1..{MAX_SIDE} px a side, got {w0}x{h0}")
    if (h0, w0) == tuple(size):
        return frames
    batch = frames if frames.ndim == 4 else frames[None]
    x = torch.from_numpy(np.ascontiguousarray(batch)).permute(0, 3, 1, 2).float()
    if h0 >= size[0] and w0 >= size[1]:
        y = F.interpolate(x, size=size, mode="area")  # box average (OpenCV's INTER_AREA): no aliasing
    else:
        y = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    out = y.round_().clamp_(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous().numpy()
    return out if frames.ndim == 4 else out[0]


def to_tensor(frames: UInt8Image | torch.Tensor) -> torch.Tensor:
    """uint8 (N, H, W, 3) → float32 (N, 3, H, W) in [0, 1], the networks' image input."""
    x = frames if isinstance(frames, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(frames))
    return x.permute(0, 3, 1, 2).float().div_(255.0)


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Training augmentation: shift each image by up to ``pad`` px, edges repeated (DrQ's random shift).

    Args:
        images: float (B, 3, H, W).
        pad: Largest shift [px] along each axis.

    Returns:
        float (B, 3, H, W).
    """
    b, _, h, w = images.shape
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (b,), generator=generator).tolist()
    dy = torch.randint(0, 2 * pad + 1, (b,), generator=generator).tolist()
    return torch.stack(
        [padded[i, :, y : y + h, x : x + w] for i, (x, y) in enumerate(zip(dx, dy, strict=True))]
    )
