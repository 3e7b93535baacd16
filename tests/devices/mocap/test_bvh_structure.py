"""Real BVH files: units from body proportions (CMU's 0.056444 m, cm, m) and the arm joints found by the
skeleton's structure whatever their names (LeftArm/LeftForeArm/LeftHand or LeftShoulder/LeftElbow/
LeftWrist) (issue 11, finding 11)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from telerig.devices.mocap import BvhPlayer
from telerig.devices.mocap.bvh import CMU_UNIT_M, body_keypoints, detect_scale, parse_bvh

#: A joint: name, offset from its parent [m] in BVH axes (Y up, +Z forward, +X the performer's left),
#: children. A leaf gets an End Site at ``end`` [m].
Joint = tuple[str, tuple[float, float, float], list["Joint"]]


def _leg(side: str, names: tuple[str, ...], lead: bool) -> Joint:
    x = 0.09 if side == "L" else -0.09
    knee: Joint = (names[2], (0.0, -0.42, 0.0), [(names[3], (0.0, -0.40, 0.0), [])])
    hip: Joint = (names[1], (x, -0.06, 0.0), [knee])
    return (names[0], (0.0, 0.0, 0.0), [hip]) if lead else hip


def _arm(side: str, names: tuple[str, str, str, str], fingers: bool) -> Joint:
    s = 1.0 if side == "L" else -1.0
    hand: list[Joint] = []
    if fingers:  # CMU: LeftHand -> LeftFingerBase -> LeftHandIndex1, and LThumb
        hand = [
            (
                f"{names[3]}FingerBase",
                (s * 0.10, 0.0, 0.0),
                [(f"{names[3]}Index1", (s * 0.04, 0.0, 0.0), [])],
            ),
            (f"{side}Thumb", (s * 0.03, 0.0, 0.03), []),
        ]
    wrist: Joint = (names[3], (s * 0.25, 0.0, 0.0), hand)
    elbow: Joint = (names[2], (s * 0.29, 0.0, 0.0), [wrist])
    shoulder: Joint = (names[1], (s * 0.17, 0.05, 0.0), [elbow])  # the collar bone's length
    return (names[0], (0.0, 0.0, 0.0), [shoulder])


def cmu_body() -> Joint:
    """The CMU mocap database's skeleton (Hips, LHipJoint, LeftUpLeg, ..., LeftShoulder = the collar,
    LeftArm, LeftForeArm, LeftHand with finger and thumb branches), 1.60 m tall."""
    spine: Joint = (
        "LowerBack",
        (0.0, 0.0, 0.0),
        [
            (
                "Spine",
                (0.0, 0.12, 0.0),
                [
                    (
                        "Spine1",
                        (0.0, 0.25, 0.0),
                        [
                            ("Neck", (0.0, 0.10, 0.0), [("Head", (0.0, 0.12, 0.0), [])]),
                            _arm("L", ("LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"), True),
                            _arm("R", ("RightShoulder", "RightArm", "RightForeArm", "RightHand"), True),
                        ],
                    )
                ],
            )
        ],
    )
    legs = [
        _leg("L", ("LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot"), True),
        _leg("R", ("RHipJoint", "RightUpLeg", "RightLeg", "RightFoot"), True),
    ]
    return ("Hips", (0.0, 0.0, 0.0), [*legs, spine])


def anatomical_body() -> Joint:
    """The other common naming (LeftCollar, LeftShoulder = the shoulder, LeftElbow, LeftWrist; LeftHip,
    LeftKnee, LeftAnkle), hands without fingers, 1.60 m tall."""
    chest: Joint = (
        "Chest",
        (0.0, 0.25, 0.0),
        [
            ("Neck", (0.0, 0.10, 0.0), [("Head", (0.0, 0.12, 0.0), [])]),
            _arm("L", ("LeftCollar", "LeftShoulder", "LeftElbow", "LeftWrist"), False),
            _arm("R", ("RightCollar", "RightShoulder", "RightElbow", "RightWrist"), False),
        ],
    )
    legs = [
        _leg("L", ("", "LeftHip", "LeftKnee", "LeftAnkle"), False),
        _leg("R", ("", "RightHip", "RightKnee", "RightAnkle"), False),
    ]
    return ("Hips", (0.0, 0.0, 0.0), [*legs, ("Spine", (0.0, 0.12, 0.0), [chest])])


#: Standing height of both bodies: hips 0.88 m above the ankles, head end 0.13 m above the Head joint.
HEIGHT_M = 0.88 + 0.12 + 0.25 + 0.10 + 0.12 + 0.13
HIPS_M = 0.06 + 0.42 + 0.40


def bvh_text(body: Joint, unit_m: float, frames: int = 3) -> str:
    """BVH text of ``body`` in units of ``unit_m`` [m], the header layout of the CMU database's BVH release
    (ROOT with 6 channels Z-Y-X, every joint 3 rotation channels), standing still."""
    lines = ["HIERARCHY"]
    columns = 0

    def write(joint: Joint, depth: int, root: bool) -> None:
        nonlocal columns
        name, offset, children = joint
        pad = "\t" * depth
        lines.append(f"{pad}{'ROOT' if root else 'JOINT'} {name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET " + " ".join(f"{v / unit_m:.6f}" for v in offset))
        if root:
            lines.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation")
            columns += 6
        else:
            lines.append(f"{pad}\tCHANNELS 3 Zrotation Yrotation Xrotation")
            columns += 3
        for child in children:
            write(child, depth + 1, False)
        if not children:
            end = 0.13 if name == "Head" else 0.05
            lines.extend(
                [f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET 0 {end / unit_m:.6f} 0", f"{pad}\t}}"]
            )
        lines.append(f"{pad}}}")

    write(body, 0, True)
    row = [0.0] * columns
    row[1] = HIPS_M / unit_m
    lines += ["MOTION", f"Frames: {frames}", "Frame Time: 0.008333"]
    lines += [" ".join(f"{v:.6f}" for v in row)] * frames
    return "\n".join(lines) + "\n"


BODIES = {"cmu_names": cmu_body, "anatomical_names": anatomical_body}
UNITS = {"cmu_units": CMU_UNIT_M, "centimetres": 0.01, "metres": 1.0}
#: File joints of the keypoints per naming convention.
EXPECTED = {
    "cmu_names": {
        "right_shoulder": "RightArm",
        "right_elbow": "RightForeArm",
        "right_wrist": "RightHand",
        "left_shoulder": "LeftArm",
        "left_elbow": "LeftForeArm",
        "left_wrist": "LeftHand",
        "right_hip": "RightUpLeg",
        "left_hip": "LeftUpLeg",
    },
    "anatomical_names": {
        "right_shoulder": "RightShoulder",
        "right_elbow": "RightElbow",
        "right_wrist": "RightWrist",
        "left_shoulder": "LeftShoulder",
        "left_elbow": "LeftElbow",
        "left_wrist": "LeftWrist",
        "right_hip": "RightHip",
        "left_hip": "LeftHip",
    },
}


def test_the_cmu_unit_is_a_0_45th_of_an_inch() -> None:
    # The CMU database's ASF skeletons are in inches scaled by 0.45 ("length 0.45" in their units block).
    assert pytest.approx(0.056444, abs=1e-6) == CMU_UNIT_M


@pytest.mark.parametrize("unit", UNITS)
@pytest.mark.parametrize("body", BODIES)
def test_scale_is_detected_from_body_proportions(body: str, unit: str) -> None:
    clip = parse_bvh(bvh_text(BODIES[body](), UNITS[unit]))
    assert detect_scale(clip) == pytest.approx(UNITS[unit])


@pytest.mark.parametrize("body", BODIES)
def test_a_cmu_file_plays_a_person_of_their_height(body: str, tmp_path: Path) -> None:
    path = tmp_path / "cmu.bvh"
    path.write_text(bvh_text(BODIES[body](), CMU_UNIT_M))
    frame = BvhPlayer(path).frames()[0]
    height = float(np.ptp(frame.positions[:, 2]))
    assert height == pytest.approx(HEIGHT_M, abs=0.01)  # in centimetres it came out 0.1 m tall


@pytest.mark.parametrize("body", BODIES)
def test_keypoint_joints_are_found_by_structure(body: str) -> None:
    clip = parse_bvh(bvh_text(BODIES[body](), 0.01))
    found = {k: clip.joints[j].name for k, j in body_keypoints(clip).items()}
    assert found == EXPECTED[body]


def test_an_upper_body_file_still_gets_its_arms_and_scale() -> None:
    # No legs: the arms alone give the scale and the keypoints.
    name, offset, children = anatomical_body()
    spine = [c for c in children if c[0] == "Spine"]
    clip = parse_bvh(bvh_text((name, offset, spine), CMU_UNIT_M))
    assert detect_scale(clip) == pytest.approx(CMU_UNIT_M)
    found = {k: clip.joints[j].name for k, j in body_keypoints(clip).items()}
    assert found == {k: v for k, v in EXPECTED["anatomical_names"].items() if not k.endswith("_hip")}


@pytest.mark.parametrize("body", BODIES)
def test_the_player_names_the_arm_joints_the_way_the_retargeter_reads_them(body: str, tmp_path: Path) -> None:
    path = tmp_path / "body.bvh"
    path.write_text(bvh_text(BODIES[body](), 0.01))
    clip = parse_bvh(path.read_text())
    frame = BvhPlayer(path).frames()[0]
    file_names = [j.name for j in clip.joints]
    # CMU names for the keypoints (the convention the humanoid retargeter's "cmu" profile reads),
    # at the positions of the joints the structure found.
    cmu = EXPECTED["cmu_names"]
    for keypoint, file_joint in EXPECTED[body].items():
        row = file_names.index(file_joint)
        assert frame.joint_names[row] == cmu[keypoint]
    kept = [n for n in file_names if n not in EXPECTED[body].values()]
    assert set(kept) <= set(frame.joint_names)  # the other joints keep the file's names
    assert len(set(frame.joint_names)) == len(frame.joint_names)
    raw = BvhPlayer(path, normalize_names=False).frames()[0]
    assert raw.joint_names == tuple(file_names)
