"""The robots' drawn-only meshes are simplified when a model compiles; physics stays exactly the same."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import fast_simplification  # type: ignore[import-untyped]
import mujoco
import numpy as np
import pytest
from pydantic import ValidationError

from telerig.robots.models import mjcf, visual_meshes
from telerig.robots.models.arm import ArmScene, build_arm_kinematics
from telerig.robots.models.g1 import HumanoidScene, build_humanoid_kinematics
from telerig.robots.models.mjcf import COLLISION_GROUP, VISUAL_GROUPS
from telerig.robots.models.tiago import TiagoScene, build_tiago_kinematics
from telerig.robots.models.visual_meshes import VISUAL_MESH_FACES, visual_mesh_budget
from telerig.robots.sim.config import MujocoArmConfig, MujocoGripperConfig
from telerig.robots.sim.gripper import build_gripper_scene
from telerig.robots.sim.hand import build_hand_scene
from telerig.robots.sim.humanoid import build_humanoid_scene
from telerig.robots.sim.scene import build_arm_scene
from telerig.robots.sim.tiago import build_tiago_scene

pytestmark = pytest.mark.sim

# robosuite MJCF (UR5e + Robotiq, TIAGo), a URDF whose visual and collision geoms share mesh files
# (G1), and a hand (Ability).
BUILDERS: dict[str, Callable[[], mujoco.MjModel]] = {
    "ur5e": lambda: build_arm_scene("ur5e_robotiq85").model,
    "tiago": lambda: build_tiago_scene().model,
    "g1": lambda: build_humanoid_scene().model,
    "ability": lambda: build_hand_scene("ability").model,
}


@pytest.fixture(scope="module")
def pairs() -> dict[str, tuple[mujoco.MjModel, mujoco.MjModel]]:
    """Scene name -> (every face, simplified)."""
    out = {}
    for name, build in BUILDERS.items():
        with visual_mesh_budget(0):
            full = build()
        out[name] = (full, build())
    return out


def _mesh(model: mujoco.MjModel, mesh: int) -> tuple[np.ndarray, np.ndarray]:
    v0, nv = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
    f0, nf = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
    return model.mesh_vert[v0 : v0 + nv], model.mesh_face[f0 : f0 + nf]


def _colliding(model: mujoco.MjModel, g: int) -> bool:
    return bool(model.geom_contype[g] or model.geom_conaffinity[g] or model.geom_group[g] == COLLISION_GROUP)


def _drawn_mesh_faces(model: mujoco.MjModel) -> int:
    return sum(
        int(model.mesh_facenum[model.geom_dataid[g]])
        for g in range(model.ngeom)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] in VISUAL_GROUPS
    )


@pytest.mark.parametrize("name", list(BUILDERS))
def test_masses_inertias_and_collision_geoms_are_exactly_the_full_models(
    pairs: dict[str, tuple[mujoco.MjModel, mujoco.MjModel]], name: str
) -> None:
    full, simple = pairs[name]
    assert (full.nbody, full.njnt, full.ngeom, full.nq, full.nu) == (
        simple.nbody,
        simple.njnt,
        simple.ngeom,
        simple.nq,
        simple.nu,
    )
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "qpos0", "dof_armature"):
        np.testing.assert_array_equal(getattr(full, field), getattr(simple, field), err_msg=field)
    collision = [g for g in range(full.ngeom) if _colliding(full, g)]
    assert collision == [g for g in range(simple.ngeom) if _colliding(simple, g)]
    for field in (
        "geom_type",
        "geom_size",
        "geom_pos",
        "geom_quat",
        "geom_contype",
        "geom_conaffinity",
        "geom_friction",
    ):
        np.testing.assert_array_equal(
            getattr(full, field)[collision], getattr(simple, field)[collision], err_msg=field
        )
    for g in collision:
        if full.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            for a, b in zip(
                _mesh(full, full.geom_dataid[g]), _mesh(simple, simple.geom_dataid[g]), strict=True
            ):
                np.testing.assert_array_equal(a, b)
    # ... and the camera draws a fraction of the faces, no drawn mesh more than before.
    assert _drawn_mesh_faces(simple) < _drawn_mesh_faces(full) / 2
    for g in range(simple.ngeom):
        if simple.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and not _colliding(simple, g):
            assert simple.mesh_facenum[simple.geom_dataid[g]] <= full.mesh_facenum[full.geom_dataid[g]]


@pytest.mark.parametrize("name", list(BUILDERS))
def test_simplified_meshes_sit_where_the_full_ones_do(
    pairs: dict[str, tuple[mujoco.MjModel, mujoco.MjModel]], name: str
) -> None:
    """World-frame bounding boxes of each simplified mesh within 3 mm / 3 % of the full mesh's."""
    full, simple = pairs[name]
    boxes = []
    for model in (full, simple):
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        per_geom = {}
        for g in range(model.ngeom):
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and not _colliding(model, g):
                vertices, _ = _mesh(model, model.geom_dataid[g])
                world = vertices @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
                per_geom[g] = (world.min(axis=0), world.max(axis=0))
        boxes.append(per_geom)
    simplified = [g for g in boxes[0] if full.mesh_facenum[full.geom_dataid[g]] > VISUAL_MESH_FACES]
    moved = []
    for g in simplified:
        (lo_a, hi_a), (lo_b, hi_b) = boxes[0][g], boxes[1][g]
        tolerance = max(3e-3, 0.03 * float(np.linalg.norm(hi_a - lo_a)))
        if np.abs(lo_a - lo_b).max() > tolerance or np.abs(hi_a - hi_b).max() > tolerance:
            moved.append(mujoco.mj_id2name(full, mujoco.mjtObj.mjOBJ_GEOM, g) or str(g))
    assert simplified
    assert not moved


def test_a_second_build_reuses_the_simplified_meshes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TELERIG_CACHE_DIR", str(tmp_path))  # nothing on disk yet
    calls: list[int] = []
    real = fast_simplification.simplify

    def counting(*args: object, **kwargs: object) -> object:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(fast_simplification, "simplify", counting)
    monkeypatch.setattr(visual_meshes, "_SIMPLIFIED", {})
    first = build_gripper_scene().model
    assert calls
    count = len(calls)
    second = build_gripper_scene().model
    assert len(calls) == count  # nothing simplified again
    np.testing.assert_array_equal(first.mesh_vert, second.mesh_vert)
    np.testing.assert_array_equal(first.mesh_face, second.mesh_face)


def test_a_budget_of_zero_keeps_every_face_and_a_bad_budget_says_what_to_fix() -> None:
    spec = mujoco.MjSpec()
    with pytest.raises(ValueError, match="visual_mesh_faces must be 0"):
        mjcf.compile_spec(spec, visual_mesh_faces=-1)
    with pytest.raises(ValueError, match="visual_mesh_faces must be 0"), visual_mesh_budget(3):
        pass
    with visual_mesh_budget(0):
        assert visual_meshes.budget() == 0
    assert visual_meshes.budget() == VISUAL_MESH_FACES


def test_a_rig_can_ask_for_full_detail_renders_in_the_robot_config() -> None:
    full = MujocoGripperConfig(id="grip0", visual_mesh_faces=0, realtime=False).build().scene.model
    default = MujocoGripperConfig(id="grip0", realtime=False).build().scene.model
    coarse = MujocoGripperConfig(id="grip0", visual_mesh_faces=200, realtime=False).build().scene.model
    assert _drawn_mesh_faces(full) == 15_774  # robosuite's Robotiq 2F-85, every face
    assert _drawn_mesh_faces(coarse) < _drawn_mesh_faces(default) < _drawn_mesh_faces(full)
    np.testing.assert_array_equal(full.body_inertia, coarse.body_inertia)
    assert visual_meshes.budget() == VISUAL_MESH_FACES  # the budget applied to that build only
    with pytest.raises(ValidationError, match="visual_mesh_faces must be 0"):
        MujocoArmConfig(id="arm0", visual_mesh_faces=3)
    with pytest.raises(ValidationError):
        MujocoArmConfig(id="arm0", visual_mesh_faces=-1)


KINEMATICS: dict[str, Callable[[bool], ArmScene | TiagoScene | HumanoidScene]] = {
    "ur5e": lambda drawn: build_arm_kinematics("ur5e_robotiq85", drawn=drawn),
    "panda": lambda drawn: build_arm_kinematics("panda", drawn=drawn),
    "tiago": lambda drawn: build_tiago_kinematics(drawn=drawn),
    "g1": lambda drawn: build_humanoid_kinematics(drawn=drawn),
}


@pytest.mark.parametrize("name", list(KINEMATICS))
def test_kinematic_models_leave_out_what_only_draws_and_keep_bodies_sites_and_collisions(name: str) -> None:
    drawn = KINEMATICS[name](True).model
    bare = KINEMATICS[name](False).model
    assert (bare.nbody, bare.njnt, bare.nq, bare.nsite) == (drawn.nbody, drawn.njnt, drawn.nq, drawn.nsite)

    # Most meshes only a camera draws are gone (what adds mass to a body stays); every colliding geom
    # is there, in the same order.
    def drawn_meshes(model: mujoco.MjModel) -> list[int]:
        return [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]

    def colliding(model: mujoco.MjModel) -> list[int]:
        return [g for g in range(model.ngeom) if _colliding(model, g)]

    only_drawn = [g for g in drawn_meshes(drawn) if not _colliding(drawn, g)]
    assert len([g for g in drawn_meshes(bare) if not _colliding(bare, g)]) < len(only_drawn) / 4
    for field in ("geom_type", "geom_size", "geom_bodyid", "geom_pos", "geom_contype", "geom_conaffinity"):
        np.testing.assert_array_equal(
            getattr(drawn, field)[colliding(drawn)], getattr(bare, field)[colliding(bare)], err_msg=field
        )
    for field in ("body_pos", "body_quat", "jnt_range", "jnt_axis", "site_pos", "site_bodyid"):
        np.testing.assert_array_equal(getattr(drawn, field), getattr(bare, field), err_msg=field)
    # The same forward kinematics and the same contacts at a random configuration.
    rng = np.random.default_rng(0)
    q = rng.uniform(drawn.jnt_range[:, 0], drawn.jnt_range[:, 1])
    data = {}
    for label, model in (("drawn", drawn), ("bare", bare)):
        d = mujoco.MjData(model)
        d.qpos[:] = q
        mujoco.mj_kinematics(model, d)
        mujoco.mj_collision(model, d)
        data[label] = d
    np.testing.assert_allclose(data["drawn"].site_xpos, data["bare"].site_xpos, atol=1e-12)
    np.testing.assert_allclose(data["drawn"].xpos, data["bare"].xpos, atol=1e-12)
    assert data["drawn"].ncon == data["bare"].ncon


def _build_in_a_fresh_process() -> tuple[float, int]:
    """Build the gripper scene in a new interpreter: (seconds, fast_simplification calls)."""
    code = (
        "import time, fast_simplification as fs\n"
        "calls = []\n"
        "real = fs.simplify\n"
        "fs.simplify = lambda *a, **k: calls.append(1) or real(*a, **k)\n"
        "from telerig.robots.sim.gripper import build_gripper_scene\n"
        "t = time.perf_counter(); build_gripper_scene(); print(time.perf_counter() - t, len(calls))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    seconds, calls = out.split()
    return float(seconds), int(calls)


def test_simplified_meshes_are_kept_on_disk_for_the_next_process(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TELERIG_CACHE_DIR", str(tmp_path))
    _, first = _build_in_a_fresh_process()
    entries = sorted((tmp_path / "visual-meshes").glob("*.npz"))
    assert first > 0  # simplified ...
    assert entries  # ... and kept, where no other user can write
    assert (tmp_path / "visual-meshes").stat().st_mode & 0o777 == 0o700
    _, second = _build_in_a_fresh_process()
    assert second == 0  # a new process reads them back instead
    # The meshes read back are the ones simplified: the same model as this process builds.
    monkeypatch.setattr(visual_meshes, "_SIMPLIFIED", {})
    from_disk = build_gripper_scene().model
    visual_meshes.clear_cache()
    monkeypatch.setenv("TELERIG_CACHE_DIR", str(tmp_path / "elsewhere"))
    fresh = build_gripper_scene().model
    np.testing.assert_array_equal(from_disk.mesh_vert, fresh.mesh_vert)
    np.testing.assert_array_equal(from_disk.mesh_face, fresh.mesh_face)


@pytest.mark.parametrize(
    "damage",
    [
        b"",
        b"not a zip file",
        b"PK\x03\x04" + b"\x00" * 64,
        "faces out of range",
        "NaN vertices",
        "wrong shape",
        "wrapping index",
    ],
    ids=[
        "empty",
        "not zip",
        "bad zip",
        "faces out of range",
        "NaN vertices",
        "wrong shape",
        "wrapping index",
    ],
)
def test_a_damaged_cache_entry_is_simplified_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, damage: bytes | str
) -> None:
    monkeypatch.setenv("TELERIG_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(visual_meshes, "_SIMPLIFIED", {})
    good = build_gripper_scene().model
    entries = sorted((tmp_path / "visual-meshes").glob("*.npz"))
    assert entries
    for entry in entries:
        if isinstance(damage, bytes):
            entry.write_bytes(damage)
            continue
        with np.load(entry) as z:
            vertices, faces = z["vertices"], z["faces"]
        if not len(faces):
            continue
        if damage == "faces out of range":
            faces = faces + len(vertices)
        elif damage == "wrapping index":  # cast to int32: in range, but every face turned over
            faces = faces[:, ::-1].astype(np.int64) + (1 << 32)
        elif damage == "NaN vertices":
            vertices = np.full_like(vertices, np.nan)
        else:
            vertices = vertices.reshape(-1)
        with entry.open("wb") as f:
            np.savez(f, vertices=vertices, faces=faces)
    monkeypatch.setattr(visual_meshes, "_SIMPLIFIED", {})
    again = build_gripper_scene().model
    np.testing.assert_array_equal(good.mesh_vert, again.mesh_vert)
    np.testing.assert_array_equal(good.mesh_face, again.mesh_face)


def test_a_cache_that_cannot_be_written_only_costs_the_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    blocked = tmp_path / "a-file"
    blocked.write_text("not a directory")
    monkeypatch.setenv("TELERIG_CACHE_DIR", str(blocked))
    monkeypatch.setattr(visual_meshes, "_SIMPLIFIED", {})
    model = build_gripper_scene().model
    assert _drawn_mesh_faces(model) > 0
    assert blocked.read_text() == "not a directory"
