"""Policy checkpoints: round trip, content hash, atomic write, and one-line errors on damage."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from telerig.errors import PolicyError
from telerig.policy.checkpoint import (
    MAX_CHECKPOINT_BYTES,
    Checkpoint,
    Normalization,
    content_hash,
    load_checkpoint,
    save_checkpoint,
    tiny_for_tests,
)
from telerig.policy.models import ModelConfig, PolicyType, build_model


@pytest.mark.parametrize("policy_type", ["bc", "act_lite"])
def test_round_trip_keeps_everything_and_the_hash(tmp_path: Path, policy_type: PolicyType) -> None:
    path = tmp_path / "p.pt"
    written = tiny_for_tests(
        path, policy_type, camera_keys=("scene", "wrist"), rig="demo", rig_fingerprint="ab12"
    )
    loaded = load_checkpoint(path)
    assert loaded.model == written.model
    assert loaded.state_names == written.state_names
    assert loaded.action_names == written.action_names
    assert loaded.camera_keys == ("scene", "wrist")
    assert loaded.image_size == (24, 32)
    assert (loaded.fps, loaded.chunk_size, loaded.rig, loaded.rig_fingerprint) == (30.0, 4, "demo", "ab12")
    assert loaded.state_dict.keys() == written.state_dict.keys()
    for name, tensor in written.state_dict.items():
        assert torch.equal(loaded.state_dict[name], tensor), name
    assert loaded.sha256 == written.sha256
    assert len(loaded.sha256) == 64
    assert loaded.id == loaded.sha256[:12]
    # The hash says what the policy is: rewriting the same content gives the same id.
    save_checkpoint(loaded, tmp_path / "copy.pt")
    assert load_checkpoint(tmp_path / "copy.pt").sha256 == written.sha256


def test_hash_changes_with_any_weight_or_metadata(tmp_path: Path) -> None:
    base = tiny_for_tests(tmp_path / "a.pt")
    meta = base.meta_json()
    state = {k: v.clone() for k, v in base.state_dict.items()}
    assert content_hash(meta, state) == base.sha256
    name = sorted(state)[0]
    state[name].view(-1)[0] += 1e-6
    assert content_hash(meta, state) != base.sha256
    assert tiny_for_tests(tmp_path / "b.pt", seed=1).sha256 != base.sha256
    assert tiny_for_tests(tmp_path / "c.pt", fps=15.0).sha256 != base.sha256
    assert tiny_for_tests(tmp_path / "d.pt").sha256 == base.sha256  # same seed, same content


def test_normalization_round_trip() -> None:
    rng = np.random.default_rng(0)
    state = rng.normal([0.5, -1.0, 2.0], [0.1, 2.0, 0.0], size=(500, 3))  # third entry never moves
    action = rng.normal([1.0, 0.0], [0.3, 5.0], size=(500, 2))
    norm = Normalization.fit(state, action)
    z = norm.normalize_action(action)
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=1e-4)
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=1e-3)
    np.testing.assert_allclose(norm.denormalize_action(z), action, rtol=1e-5, atol=1e-5)
    s = norm.normalize_state(state)
    assert np.isfinite(s).all()  # the constant entry is divided by MIN_STD, not 0
    assert norm.state_std[2] == pytest.approx(1e-3)
    again = Normalization.from_json(json.loads(json.dumps(norm.to_json())), 3, 2)
    for key in ("state_mean", "state_std", "action_mean", "action_std"):
        np.testing.assert_array_equal(getattr(again, key), getattr(norm, key))


def test_relative_actions_are_offsets_from_the_state_they_act_on() -> None:
    rng = np.random.default_rng(1)
    state = rng.normal([0.5, -1.0, 2.0], [0.8, 1.5, 0.3], size=(400, 3))
    # Chunks of 4 actions: entry 0 a few hundredths off state entry 1, entry 1 absolute.
    offsets = rng.normal(0.02, 0.01, size=(400, 4))
    chunks = np.stack([state[:, [1]] + offsets, rng.normal(3.0, 0.5, size=(400, 4))], axis=-1)
    norm = Normalization.fit(state, chunks, relative_to=(1, -1), reference=state[:, None, :])
    # The relative entry's statistics are the offsets', not the joint's range.
    assert norm.action_mean[0] == pytest.approx(0.02, abs=2e-3)
    assert norm.action_std[0] == pytest.approx(0.01, abs=1e-3)
    assert norm.action_mean[1] == pytest.approx(3.0, abs=0.05)
    z = norm.normalize_action(chunks, state[:, None, :])
    np.testing.assert_allclose(z.reshape(-1, 2).std(axis=0), 1.0, atol=1e-3)
    np.testing.assert_allclose(norm.denormalize_action(z, state[:, None, :]), chunks, rtol=1e-5, atol=1e-5)
    # One observation: a (4, 2) chunk back in physical units from the state it was predicted on.
    np.testing.assert_allclose(norm.denormalize_action(z[7], state[7]), chunks[7], atol=1e-5)
    with pytest.raises(PolicyError, match="relative to the state: pass the state"):
        norm.denormalize_action(z[7])
    again = Normalization.from_json(json.loads(json.dumps(norm.to_json())), 3, 2)
    assert again.relative_to == (1, -1)
    # Checkpoints written before relative actions have no relative_to: every entry absolute.
    absolute = {k: v for k, v in norm.to_json().items() if k != "relative_to"}
    assert Normalization.from_json(absolute, 3, 2).relative_to == ()
    for bad in ([5, -1], [0], [0, "1"], "01", [-2, 0]):
        with pytest.raises(PolicyError, match="relative_to"):
            Normalization.from_json({**absolute, "relative_to": bad}, 3, 2)


def test_a_flipped_byte_is_refused_with_one_line(tmp_path: Path) -> None:
    path = tmp_path / "p.pt"
    tiny_for_tests(path)
    raw = torch.load(path, weights_only=True)
    raw["state_dict"][sorted(raw["state_dict"])[-1]].view(-1)[0] += 1.0  # damaged weights, valid file
    torch.save(raw, path)
    with pytest.raises(PolicyError, match="does not match its content hash") as info:
        load_checkpoint(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"", "unreadable"),
        (b"not a checkpoint at all\n" * 100, "unreadable"),
        (b"\x00" * 4096, "unreadable"),
        ("truncated", "unreadable"),
        ("random-bytes", "unreadable"),
        ("other-format", "not a telerig policy checkpoint"),
        ("future-version", "format version 99"),
        ("no-hash", "lacks its metadata"),
        ("bad-meta", "invalid metadata"),
        ("wrong-shapes", "weights do not fit"),
        ("nan-stats", "normalization"),
    ],
)
def test_garbage_checkpoints_give_one_line_errors(tmp_path: Path, content: bytes | str, match: str) -> None:
    good = tmp_path / "good.pt"
    tiny_for_tests(good)
    path = tmp_path / "bad.pt"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content == "truncated":
        data = good.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif content == "random-bytes":
        path.write_bytes(np.random.default_rng(1).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    else:
        raw = torch.load(good, weights_only=True)
        meta = json.loads(raw["meta"])
        if content == "other-format":
            raw["format"] = "lerobot"
        elif content == "future-version":
            raw["version"] = 99
        elif content == "no-hash":
            del raw["sha256"]
        elif content == "bad-meta":
            del meta["state_names"]
        elif content == "wrong-shapes":
            meta["model"]["hidden"] = 48
        elif content == "nan-stats":
            meta["normalization"]["action_std"][0] = -1.0
        if content in ("bad-meta", "wrong-shapes", "nan-stats"):
            raw["meta"] = json.dumps(meta, sort_keys=True)
            raw["sha256"] = content_hash(raw["meta"], raw["state_dict"])  # consistent hash, bad content
        buffer = io.BytesIO()
        torch.save(raw, buffer)
        path.write_bytes(buffer.getvalue())
    with pytest.raises(PolicyError, match=match) as info:
        load_checkpoint(path)
    assert "\n" not in str(info.value)


def test_missing_checkpoint_names_the_fix(tmp_path: Path) -> None:
    with pytest.raises(PolicyError, match="does not exist"):
        load_checkpoint(tmp_path / "nope.pt")
    with pytest.raises(PolicyError, match="does not exist"):
        load_checkpoint(tmp_path)


def test_save_is_atomic_and_keeps_the_old_file_on_failure(tmp_path: Path) -> None:
    path = tmp_path / "p.pt"
    first = tiny_for_tests(path)
    config = ModelConfig("bc", 7, 7, ("scene",), (24, 32), 4)
    bad = Checkpoint(
        model=config,
        state_dict=build_model(config).state_dict(),
        normalization=first.normalization,
        state_names=first.state_names,
        action_names=first.action_names,
        fps=30.0,
        training={"not json": object()},
    )
    with pytest.raises(PolicyError, match="not plain JSON"):
        save_checkpoint(bad, path)
    assert load_checkpoint(path).sha256 == first.sha256
    assert [p.name for p in tmp_path.iterdir()] == ["p.pt"]  # no temp file left behind


def test_checkpoint_refuses_names_that_do_not_fit_the_model() -> None:
    config = ModelConfig("bc", 3, 2, (), (24, 32), 4)
    norm = Normalization(
        np.zeros(3, np.float32), np.ones(3, np.float32), np.zeros(2, np.float32), np.ones(2, np.float32)
    )
    with pytest.raises(PolicyError, match="2 state names for a state of 3"):
        Checkpoint(config, build_model(config).state_dict(), norm, ("a", "b"), ("x", "y"), 30.0)
    with pytest.raises(PolicyError, match="fps must be > 0"):
        Checkpoint(config, build_model(config).state_dict(), norm, ("a", "b", "c"), ("x", "y"), 0.0)


class _Payload:
    """Unpickling this would run ``os.system``: a checkpoint must never be able to do that."""

    def __reduce__(self) -> tuple[object, tuple[str]]:
        import os

        return (os.system, ("touch pwned",))


def test_a_checkpoint_that_would_run_code_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "evil.pt"
    torch.save({"format": "telerig-policy", "version": 1, "payload": _Payload()}, path)
    with pytest.raises(PolicyError, match="unreadable") as info:
        load_checkpoint(path)
    assert "\n" not in str(info.value)
    assert not (tmp_path / "pwned").exists()
    assert not Path("pwned").exists()


def test_an_oversized_file_is_refused_before_it_is_read(tmp_path: Path) -> None:
    path = tmp_path / "huge.pt"
    with open(path, "wb") as f:  # sparse: no disk space used
        f.truncate(MAX_CHECKPOINT_BYTES + 1)
    with pytest.raises(PolicyError, match="more than a telerig policy can be") as info:
        load_checkpoint(path)
    assert "\n" not in str(info.value)
