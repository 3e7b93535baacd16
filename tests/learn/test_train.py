"""telerig train on a real export: loss goes down, artifacts are written, the checkpoint runs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from telerig.cli.main import main
from telerig.errors import PolicyError
from telerig.learn.dataset import PolicyDataset, read_dataset
from telerig.learn.train import TrainConfig, artifact_paths, train
from telerig.policy.checkpoint import load_checkpoint
from telerig.policy.models import ModelConfig, PolicyType, build_model
from telerig.policy.runner import load_policy


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("train-cache")


@pytest.fixture(scope="module")
def dataset(lerobot_export: Path, cache_dir: Path) -> PolicyDataset:
    return read_dataset(lerobot_export, image_width=32, cache_dir=cache_dir)


def _tiny(policy_type: PolicyType, **overrides: object) -> TrainConfig:
    settings: dict[str, object] = {
        "steps": 60,
        "batch_size": 16,
        "lr": 3e-3 if policy_type == "bc" else 2e-3,
        "warmup_steps": 5,
        "eval_every": 30,
        "chunk_size": 4,
        "image_width": 32,
        "val_fraction": 0.5,
        "threads": 1,
        "hidden": 64,
        "layers": 1,
        "channels": (8, 16),
        "keypoints": 8,
    }
    settings.update(overrides)
    return TrainConfig.for_policy(policy_type, **settings)


@pytest.mark.parametrize(("policy_type", "relative"), [("bc", True), ("bc", False), ("act_lite", True)])
def test_a_tiny_run_reduces_the_loss_and_writes_a_runnable_checkpoint(
    dataset: PolicyDataset, tmp_path: Path, policy_type: PolicyType, relative: bool
) -> None:
    out = tmp_path / "policy.pt"
    steps_seen: list[int] = []
    config = _tiny(policy_type, relative_actions=relative)
    result = train(dataset, out, config, progress=lambda p: steps_seen.append(p.step))
    assert steps_seen == list(range(1, 61))
    assert result.fit_after < 0.8 * result.fit_before, (result.fit_before, result.fit_after)
    assert len(result.loss) == 60
    assert [s for s, _ in result.val_loss] == [30, 60]
    # Joint actions are offsets from the joints they act on; the gripper's stays absolute.
    joints = [a.part == "joints" for a in dataset.schema.action]
    assert any(joints)
    assert not all(joints)
    relative_to = (
        tuple(dataset.state_names.index(a.name) if a.part == "joints" else -1 for a in dataset.schema.action)
        if relative
        else ()
    )
    assert result.checkpoint.normalization.relative_to == relative_to
    assert (len(result.train_episodes), len(result.val_episodes)) == (1, 1)
    ckpt_path, plot_path, report_path = artifact_paths(out)
    assert result.plot_path == plot_path == tmp_path / "policy.loss.png"
    assert plot_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads(report_path.read_text())
    assert report["id"] == result.checkpoint.id
    assert len(report["loss"]) == 60
    loaded = load_checkpoint(ckpt_path)
    assert loaded.sha256 == result.checkpoint.sha256
    assert loaded.policy_type == policy_type
    assert loaded.state_names == dataset.state_names
    assert loaded.rig_fingerprint == dataset.schema.fingerprint
    assert loaded.training["dataset_digest"] == dataset.digest
    # The trained policy runs on a dataset frame and answers in the dataset's units.
    episode = dataset.episodes[result.train_episodes[0]]
    runner = load_policy(ckpt_path)
    chunk = runner.act(episode.state[10], {"scene": episode.images["scene"][10]})
    assert chunk.shape == (4, len(dataset.action_names))
    spread = float(np.abs(episode.action).max()) + 1.0
    assert np.abs(chunk).max() < 10 * spread


def test_the_same_seed_gives_the_same_checkpoint_id(dataset: PolicyDataset, tmp_path: Path) -> None:
    config = _tiny("bc", steps=6, eval_every=3)
    first = train(dataset, tmp_path / "a.pt", config)
    second = train(dataset, tmp_path / "b.pt", config)
    third = train(dataset, tmp_path / "c.pt", dataclasses.replace(config, seed=1))
    assert first.checkpoint.id == second.checkpoint.id
    assert third.checkpoint.id != first.checkpoint.id


def test_cli_trains_from_the_dataset_directory(
    lerobot_export: Path,
    dataset: PolicyDataset,
    cache_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "cli.pt"
    argv = ["train", str(lerobot_export), "--policy", "act-lite", "--out", str(out), "--steps", "3"]
    argv += [
        "--batch",
        "4",
        "--chunk",
        "4",
        "--image-width",
        "32",
        "--cache",
        str(cache_dir),
        "--threads",
        "1",
    ]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "act_lite: 3 steps" in printed
    assert load_checkpoint(out).id in printed
    assert out.with_name("cli.loss.png").is_file()


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--policy", "bc"], "is not a directory"),
        (["--policy", "bc", "--steps", "0"], "train steps must be >= 1"),
        (["--policy", "act-lite", "--batch", "-3"], "train batch-size must be >= 1"),
        (["--policy", "bc", "--lr", "nan"], "learning rate must be > 0"),
        (["--policy", "bc", "--gripper-weight", "0"], "gripper weight must be > 0"),
        (["--policy", "bc", "--gripper-weight", "inf"], "gripper weight must be > 0"),
    ],
)
def test_cli_refuses_bad_input_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], match: str
) -> None:
    assert main(["train", str(tmp_path / "nope"), "--out", str(tmp_path / "p.pt"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert match in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "p.pt").exists()


def test_out_that_is_a_directory_is_refused(dataset: PolicyDataset, tmp_path: Path) -> None:
    with pytest.raises(PolicyError, match="is a directory; name the checkpoint file"):
        train(dataset, tmp_path, _tiny("bc", steps=1))


def test_failed_episodes_are_left_out_unless_asked(dataset: PolicyDataset, tmp_path: Path) -> None:
    failed = dataclasses.replace(
        dataset, episodes=tuple(dataclasses.replace(e, outcome="failure") for e in dataset.episodes)
    )
    with pytest.raises(PolicyError, match="--include-failures trains on them"):
        train(failed, tmp_path / "p.pt", _tiny("bc", steps=1))
    result = train(failed, tmp_path / "p.pt", _tiny("bc", steps=2, include_failures=True))
    assert len(result.train_episodes) + len(result.val_episodes) == 2


def test_gripper_weight_weighs_the_gripper_in_the_loss(dataset: PolicyDataset, tmp_path: Path) -> None:
    gripper = [i for i, a in enumerate(dataset.schema.action) if a.part == "gripper"]
    assert gripper, "the export's actions name a gripper"
    model = build_model(
        ModelConfig("bc", len(dataset.state_names), len(dataset.action_names), (), (8, 8), chunk_size=2)
    )
    pred = torch.zeros(3, 2, len(dataset.action_names))
    target = torch.zeros_like(pred)
    target[..., gripper] = 1.0  # the only error is the gripper's
    ones = torch.ones(len(dataset.action_names))
    assert model.loss(pred, target, ones).item() == pytest.approx(model.loss(pred, target).item())
    weights = ones.clone()
    weights[gripper] = 5.0
    weighted = model.loss(pred, target, weights).item()
    # Weighted mean: the gripper's share of the error grows from 1/A to 5/(A + 4) per gripper entry.
    a, g = len(dataset.action_names), len(gripper)
    assert weighted == pytest.approx(5.0 * g / (a - g + 5.0 * g))
    assert weighted > model.loss(pred, target).item()

    result = train(dataset, tmp_path / "p.pt", _tiny("bc", steps=2, gripper_weight=5.0))
    assert json.loads(result.report_path.read_text())["gripper_weight"] == 5.0
    assert load_checkpoint(result.checkpoint_path).id == result.checkpoint.id
