"""The operator scene's geometry of the rig robots it draws beside the arms: the TIAGo mobile
manipulator and the G1 humanoid (their meshes simplified to keep the scene message small), and the
vertex clustering that does it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telerig.config import load_rig
from telerig.server.scene import MAX_MESH_BYTES, _simplify, robot_geometry

pytestmark = [pytest.mark.sim, pytest.mark.timeout(120)]


def test_vertex_clustering_merges_close_vertices_and_drops_collapsed_triangles() -> None:
    # A 1 cm grid of two triangles per cell over 10 cm x 10 cm, every vertex repeated per triangle
    # (as in an STL file), plus a sliver triangle 1 mm wide.
    xs = np.arange(0.0, 0.1001, 0.01)
    corners = [(x, y) for x in xs[:-1] for y in xs[:-1]]
    vertices: list[tuple[float, float, float]] = []
    faces: list[list[int]] = []
    for x, y in corners:
        for tri in (
            ((x, y), (x + 0.01, y), (x, y + 0.01)),
            ((x + 0.01, y), (x + 0.01, y + 0.01), (x, y + 0.01)),
        ):
            faces.append([len(vertices), len(vertices) + 1, len(vertices) + 2])
            vertices += [(a, b, 0.0) for a, b in tri]
    faces.append([len(vertices), len(vertices) + 1, len(vertices) + 2])
    vertices += [(0.0, 0.0, 0.0), (0.001, 0.0, 0.0), (0.0, 0.05, 0.0)]
    merged, triangles = _simplify(np.array(vertices), np.array(faces), 0.006)
    assert len(merged) == 121  # the grid's 11 x 11 points, each its own cell
    assert len(triangles) == 200  # the sliver collapsed, the repeats are one triangle each
    assert merged.min(axis=0) == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert merged.max(axis=0) == pytest.approx([0.1, 0.1, 0.0], abs=1e-3)


@pytest.mark.parametrize(("rig", "model"), [("tiago_wbc", "tiago"), ("mocap_g1", "g1")])
def test_the_mobile_manipulator_and_the_humanoid_are_drawn_from_small_meshes(rig: str, model: str) -> None:
    robot = load_rig(rig).robots[0]
    geometry = robot_geometry(robot)
    assert geometry.model == model
    doc = json.dumps(geometry.document())
    assert len(doc) < 1.5 * MAX_MESH_BYTES, f"{len(doc)} bytes"
    assert len(geometry.geoms) > 20
    at_home, _ = geometry.poses({})
    if model == "tiago":  # the planar base joint carries the whole robot
        moved, ee = geometry.poses({"base_x": 1.0})
        shift = np.array(moved).reshape(-1, 7)[:, :3] - np.array(at_home).reshape(-1, 7)[:, :3]
        assert shift[:, 0] == pytest.approx(1.0, abs=1e-6)
        assert ee is not None
        assert geometry.reach_m > 1.0
