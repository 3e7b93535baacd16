"""The fake Motive server serves the natnet client from PyPI (unicast) as Motive does."""

from __future__ import annotations

import json
from collections.abc import Callable

import pytest

from telerig.devices.mocap.fake import RIGID_BODY_NAMES, SKELETON_NAME, FakeNatNetServer

RunClient = Callable[..., str]


@pytest.mark.parametrize("version", ["4.1", "3.1"])
def test_natnet_client_reads_models_and_frames(version: str, run_client: RunClient) -> None:
    with FakeNatNetServer(version=version) as server:
        host, port = server.address
        out = json.loads(run_client("natnet_motive.py", host, port))
    assert out["rigid_bodies"] == [[name, i + 1] for i, name in enumerate(RIGID_BODY_NAMES)]
    assert out["skeletons"] == [[SKELETON_NAME, 1, 21]]
    numbers = [f["number"] for f in out["frames"]]
    assert numbers == list(range(numbers[0], numbers[0] + 3))
    for got in out["frames"]:
        want = server.frame_at(got["number"])
        for (body_id, pos, rot, valid), body in zip(got["bodies"], want.rigid_bodies, strict=True):
            assert body_id == body.id
            assert pos == pytest.approx(body.position, abs=1e-6)
            assert rot == pytest.approx(body.orientation, abs=1e-6)  # x, y, z, w as Motive sends it
            assert valid == bool(body.params & 1)
        assert got["skeleton_bones"] == [[1, 21]]
        assert got["labeled_markers"] == [(1 << 16) | 1]
        assert got["timestamp"] == pytest.approx(want.timestamp)
        assert got["stamp_camera_mid_exposure"] == want.stamp_camera_mid_exposure
        assert got["stamp_transmit"] == want.stamp_transmit
