"""PolicyRunner: shapes, determinism, denormalized output, the shared resize, one-line refusals."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from telerig.errors import PolicyError
from telerig.policy.checkpoint import load_checkpoint, save_checkpoint, tiny_for_tests
from telerig.policy.images import resize_rgb
from telerig.policy.runner import PolicyRunner, load_policy

RNG = np.random.default_rng(7)
FRAME = RNG.integers(0, 256, (120, 160, 3), dtype=np.uint8)
STATE = np.array([0.1, -0.4, 1.2, -1.5, 0.3, 0.0, 0.8])


@pytest.fixture(params=["bc", "act_lite"])
def checkpoint_path(tmp_path: Path, request: pytest.FixtureRequest) -> Path:
    path = tmp_path / f"{request.param}.pt"
    tiny_for_tests(path, request.param, camera_keys=("scene", "wrist"), chunk_size=5)
    return path


def test_spec_names_what_the_policy_reads_and_writes(checkpoint_path: Path) -> None:
    runner = load_policy(checkpoint_path)
    spec = runner.spec
    assert spec.state_names == ("j0", "j1", "j2", "j3", "j4", "j5", "gripper")
    assert spec.action_names == spec.state_names
    assert spec.camera_keys == ("scene", "wrist")
    assert spec.image_size == (24, 32)
    assert (spec.fps, spec.chunk_size, spec.state_dim, spec.action_dim) == (30.0, 5, 7, 7)
    assert spec.checkpoint_sha256 == load_checkpoint(checkpoint_path).sha256
    assert spec.checkpoint_id == spec.checkpoint_sha256[:12]
    assert torch.get_num_threads() == 1


def test_act_returns_a_deterministic_chunk(checkpoint_path: Path) -> None:
    runner = load_policy(checkpoint_path)
    images = {"scene": FRAME, "wrist": FRAME[::-1].copy()}
    first = runner.act(STATE, images)
    assert first.shape == (5, 7)
    assert first.dtype == np.float32
    assert np.isfinite(first).all()
    for _ in range(3):
        np.testing.assert_array_equal(runner.act(STATE, images), first)
    # A second process-like load of the same file gives the same actions.
    np.testing.assert_array_equal(load_policy(checkpoint_path).act(STATE, images), first)
    # The policy reads its inputs: another state or image changes the chunk.
    assert not np.array_equal(runner.act(STATE + 0.5, images), first)
    assert not np.array_equal(runner.act(STATE, {**images, "scene": 255 - FRAME}), first)


def test_frames_at_policy_size_and_full_size_agree(checkpoint_path: Path) -> None:
    runner = load_policy(checkpoint_path)
    small = {k: resize_rgb(f, runner.spec.image_size) for k, f in {"scene": FRAME, "wrist": FRAME}.items()}
    assert small["scene"].shape == (24, 32, 3)
    np.testing.assert_array_equal(
        runner.act(STATE, small), runner.act(STATE, {"scene": FRAME, "wrist": FRAME})
    )


def test_actions_come_out_in_physical_units(tmp_path: Path) -> None:
    path = tmp_path / "p.pt"
    ckpt = tiny_for_tests(path)
    raw = PolicyRunner(ckpt).act(STATE, {"scene": FRAME})
    norm = dataclasses.replace(
        ckpt.normalization,
        action_mean=np.arange(7, dtype=np.float32),
        action_std=np.full(7, 2.0, np.float32),
    )
    shifted = dataclasses.replace(ckpt, normalization=norm)
    save_checkpoint(shifted, path)
    np.testing.assert_allclose(
        load_policy(path).act(STATE, {"scene": FRAME}), raw * 2.0 + np.arange(7), rtol=1e-6
    )


@pytest.mark.parametrize(
    ("state", "images", "match"),
    [
        (STATE[:6], {"scene": FRAME}, r"state must have shape \(7,\)"),
        (np.full(7, np.nan), {"scene": FRAME}, "NaN or inf"),
        (np.array([np.inf, 0, 0, 0, 0, 0, 0]), {"scene": FRAME}, "NaN or inf"),
        (STATE, {}, "needs camera 'scene'"),
        (STATE, {"scene": FRAME.astype(np.float32)}, "uint8 RGB"),
        (STATE, {"scene": FRAME[..., 0]}, "uint8"),
        (STATE, {"scene": np.stack([FRAME, FRAME])}, r"one uint8 \(H, W, 3\) image"),
        (STATE, {"scene": np.zeros((0, 10, 3), np.uint8)}, "1..8192 px"),
        (STATE, {"scene": np.zeros((1, 9000, 3), np.uint8)}, "1..8192 px"),
    ],
)
def test_bad_inputs_are_refused_with_one_line(
    tmp_path: Path, state: np.ndarray, images: dict[str, np.ndarray], match: str
) -> None:
    tiny_for_tests(tmp_path / "p.pt")
    runner = load_policy(tmp_path / "p.pt")
    with pytest.raises(PolicyError, match=match) as info:
        runner.act(state, images)
    assert "\n" not in str(info.value)


def test_extreme_but_finite_inputs_still_give_finite_actions(tmp_path: Path) -> None:
    tiny_for_tests(tmp_path / "p.pt")
    runner = load_policy(tmp_path / "p.pt")
    out = runner.act(np.full(7, 1e6), {"scene": np.full((480, 640, 3), 255, np.uint8), "extra": FRAME})
    assert out.shape == (4, 7)
    assert np.isfinite(out).all()
