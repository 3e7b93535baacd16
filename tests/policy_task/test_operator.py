"""The scripted pick-and-place operator: seeded plans, what it accepts from the bus, the replay
re-targeted to a new cube, and the operator solving the task in the stepped scene through the
rig's own retargeting (no bus: deterministic)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from telerig.config import load_rig
from telerig.devices.pick_place.config import ScriptedPickPlaceConfig
from telerig.devices.pick_place.operator import ScriptedPickPlace, grasp_yaw, plan_pick_place, quat_yaw
from telerig.devices.pick_place.replay import RetargetedReplay, retarget_stream
from telerig.ir.types import ControllerState, Pose, Sample, Stamp
from telerig.retarget.binding import BindContext
from telerig.robots.sim.pick_place import draw_cube

RIG = load_rig("pick_place")
_DEVICE = RIG.devices[0]
assert isinstance(_DEVICE, ScriptedPickPlaceConfig)
DEVICE: ScriptedPickPlaceConfig = _DEVICE
FRAME = DEVICE.frame()
HOME = np.array(DEVICE.home)
TARGET = np.array([0.46, -0.15, 0.8])


def _plan(seed: int, cube_seed: int | None = None):  # type: ignore[no-untyped-def]
    draw = draw_cube(RIG.robots[0].spec(), seed if cube_seed is None else cube_seed)  # type: ignore[attr-defined]
    return plan_pick_place(seed, FRAME, HOME, draw.position, draw.yaw, TARGET)


def _trajectory(plan, dt: float = 0.01) -> np.ndarray:  # type: ignore[no-untyped-def]
    rows = []
    for k in range(int((plan.duration_s + 0.5) / dt)):
        position, yaw, trigger = plan.at(k * dt)
        rows.append([*position, yaw, trigger])
    return np.array(rows)


def test_same_seed_same_trajectory_and_seeds_vary_like_people() -> None:
    a, b = _plan(3), _plan(3)
    assert all(
        x.phase == y.phase and x.t_s == y.t_s and np.array_equal(x.position, y.position) and x.yaw == y.yaw
        for x, y in zip(a.waypoints, b.waypoints, strict=True)
    )
    assert np.array_equal(a.tremor, b.tremor)
    assert a.style == b.style
    assert np.array_equal(_trajectory(a), _trajectory(b))
    plans = [_plan(s, cube_seed=3) for s in range(12)]
    speeds = {round(p.style["speed"], 6) for p in plans}
    assert len(speeds) == 12  # the pace differs per seed
    assert any(p.style["pause_mid_s"] > 0 for p in plans)
    assert any(p.style["pause_mid_s"] == 0 for p in plans)
    durations = [p.duration_s for p in plans]
    assert max(durations) - min(durations) > 1.0
    assert all(8.0 < d < 15.0 for d in durations)


def test_plan_misses_then_corrects_and_starts_and_ends_at_home() -> None:
    plan = _plan(5)
    phases = [w.phase for w in plan.waypoints]
    assert phases[:5] == ["start", "react", "approach", "descend", "look"]
    look = plan.waypoints[phases.index("look")]
    grasp = plan.waypoints[phases.index("grasp")]
    cube = draw_cube(RIG.robots[0].spec(), 5)  # type: ignore[attr-defined]
    at_cube = FRAME.to_operator(cube.position)
    miss = float(np.hypot(*(look.position - at_cube)[:2]))
    assert miss == pytest.approx(plan.style["miss_m"], abs=1e-9)
    assert miss > 0.0
    assert float(np.hypot(*(grasp.position - at_cube)[:2])) < 0.0045  # corrected to within 4 mm
    assert look.yaw != grasp.yaw == pytest.approx(grasp_yaw(cube.yaw))
    assert np.allclose(plan.at(0.0)[0], HOME, atol=1e-3)
    end = plan.at(plan.duration_s + 2.0)
    assert np.allclose(end[0], HOME)
    assert end[2] == 0.0
    # The trigger closes only at the cube and opens only over the zone.
    traj = _trajectory(plan)
    assert traj[:, 4].max() == pytest.approx(1.0)


def test_grasp_yaw_folds_into_a_quarter_turn() -> None:
    for yaw in np.linspace(-3.0, 3.0, 25):
        g = grasp_yaw(float(yaw))
        assert -math.pi / 4 <= g < math.pi / 4
        assert math.isclose(math.remainder(g - yaw, math.pi / 2), 0.0, abs_tol=1e-9)


def _pose(source: str, position: tuple[float, float, float], frame: str = "world", seq: int = 0) -> Pose:
    t = time.time_ns()
    return Pose(Stamp(source, seq, t, t), np.array(position), np.array([1.0, 0.0, 0.0, 0.0]), frame)


def test_operator_holds_home_until_it_sees_the_cube_at_rest_and_ignores_garbage() -> None:
    device = DEVICE.build()
    assert isinstance(device, ScriptedPickPlace)
    got: list[Sample] = []
    lock = threading.Lock()

    def sink(sample: Sample) -> None:
        with lock:
            got.append(sample)

    device.start(sink)
    try:
        time.sleep(0.15)
        assert device.plan is None  # nothing observed yet: at home
        for bad in (
            _pose("arm0/cube", (math.nan, 0.0, 0.82)),
            _pose("arm0/cube", (0.5, 0.1, 0.82), frame="operator"),
            _pose("arm0/cube", (1e9, 0.1, 0.82)),
            _pose("arm9/cube", (0.5, 0.1, 0.82)),
            ControllerState(
                Stamp("arm0/cube", 0, 1, 1), "right", np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), "world"
            ),
        ):
            device.observe(bad)
        assert device.ignored == 5
        for i in range(30):
            device.observe(_pose("arm0/cube", (0.5, 0.1, 0.82), seq=i))
            device.observe(_pose("arm0/target", (0.46, -0.15, 0.8), seq=i))
            time.sleep(0.01)
        deadline = time.monotonic() + 2.0
        while device.plan is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert device.plan is not None
        assert device.plan.seed == DEVICE.seed
    finally:
        device.stop()
    with lock:
        states = [s for s in got if isinstance(s, ControllerState)]
    assert states
    assert all(s.stamp.source_id == "vr0/right" for s in states)
    assert np.allclose(states[0].position, HOME)
    seqs = [s.stamp.seq for s in states]
    assert seqs == sorted(seqs)
    # The next start is the next episode: seed + 1.
    device.start(sink)
    device.stop()
    assert device.episodes == 2


def test_replay_is_bent_to_the_new_cube_at_the_grasp_and_back_by_the_release() -> None:
    plan = _plan(4)
    old = draw_cube(RIG.robots[0].spec(), 4)  # type: ignore[attr-defined]
    new = draw_cube(RIG.robots[0].spec(), 11)  # type: ignore[attr-defined]
    device = DEVICE.build()
    assert isinstance(device, ScriptedPickPlace)
    samples = []
    for k, t in enumerate(np.arange(0.0, plan.duration_s + 0.5, 0.01)):
        position, yaw, trigger = plan.at(float(t))
        ns = int(t * 1e9)
        samples.append(device.state(Stamp("vr0/right", k, ns, ns), position, yaw, trigger))
    bent = retarget_stream(
        tuple(samples),
        FRAME,
        Pose(Stamp("arm0/cube", 0, 0, 0), old.position, old.orientation, "world"),
        Pose(Stamp("arm0/cube", 0, 0, 0), new.position, new.orientation, "world"),
    )
    grasp = next(i for i, s in enumerate(samples) if s.trigger > 0.5)
    shift = FRAME.to_operator(new.position) - FRAME.to_operator(old.position)
    assert np.allclose(bent[grasp].position - samples[grasp].position, shift, atol=1e-9)
    assert np.allclose(bent[0].position, samples[0].position)
    assert np.allclose(bent[-1].position, samples[-1].position)
    turned = quat_yaw(bent[grasp].orientation) - quat_yaw(samples[grasp].orientation)
    assert math.isclose(
        math.remainder(turned - (grasp_yaw(new.yaw) - grasp_yaw(old.yaw)), 2 * math.pi), 0, abs_tol=1e-6
    )
    assert [s.trigger for s in bent] == [s.trigger for s in samples]


def test_scripted_operator_solves_the_stepped_task() -> None:
    """The rig's own retargeters (absolute pose IK, trigger gripper) drive the stepped scene."""
    robot = RIG.robots[0].model_copy(update={"realtime": False}).build()
    robot.connect()
    try:
        parts = {
            b.target: b.retargeter.bind(
                BindContext(RIG.name, "arm0", robot, b.target, "vr0", b.part, ("vr0",))
            )
            for b in RIG.bindings
        }
        seed = 6
        robot.begin_task(seed)  # type: ignore[attr-defined]
        robot.step(25)  # type: ignore[attr-defined]
        cube, target = robot.read_object_pose("cube"), robot.read_object_pose("target")  # type: ignore[attr-defined]
        plan = plan_pick_place(seed, FRAME, HOME, cube.position, quat_yaw(cube.orientation), target.position)
        device = DEVICE.build()
        assert isinstance(device, ScriptedPickPlace)
        dt = 0.01
        for k in range(int((plan.duration_s + 1.0) / dt)):
            position, yaw, trigger = plan.at(k * dt)
            ns = int(k * dt * 1e9)
            sample = device.state(Stamp("vr0/right", k, ns, ns), position, yaw, trigger)
            arm, gripper = parts["arm"].joints, parts["gripper"].gripper
            assert arm is not None
            assert gripper is not None
            command, _ = arm(sample, robot.read_state().positions, dt)
            if command is not None:
                robot.send(command)
            grip = gripper(sample)
            if grip is not None:
                robot.send_gripper(grip)
            robot.step(5)  # type: ignore[attr-defined]
        check = robot.check_task()  # type: ignore[attr-defined]
        assert check.success, check.reason
    finally:
        robot.close()


def _retargeted_replay_of_a_recording(tmp_path: Path) -> tuple[RetargetedReplay, Pose, Pose]:
    """A 1.5 s pick recorded at 100 Hz (the trigger closes at 1.0 s) with the cube at seed 4's pose,
    as a ``replay_retargeted`` device; the recorded and a new cube pose (seed 11)."""
    from telerig.devices.pick_place.config import RetargetedReplayConfig
    from telerig.ir import wire
    from telerig.ir.mcap_log import McapLog

    plan = _plan(4)
    old = draw_cube(RIG.robots[0].spec(), 4)  # type: ignore[attr-defined]
    new = draw_cube(RIG.robots[0].spec(), 11)  # type: ignore[attr-defined]
    device = DEVICE.build()
    assert isinstance(device, ScriptedPickPlace)
    topic = "telerig/v1/pick_place/vr0/right_controller"
    path = tmp_path / "episode.mcap"
    t0 = 1_700_000_000_000_000_000
    with McapLog(path) as log:
        for k, t in enumerate(np.arange(0.0, 1.5, 0.01)):
            ns = t0 + int(t * 1e9)
            cube = Pose(Stamp("arm0/cube", k, ns, ns), old.position, old.orientation, "world")
            log.write(
                "telerig/v1/pick_place/arm0/object_pose",
                wire.encode(cube),
                log_time_ns=ns,
                publish_time_ns=ns,
            )
            # A recording squeezed to 1.5 s: the trigger closes at 1.0 s.
            position, yaw, _ = plan.at(float(t) * plan.duration_s / 1.5)
            sample = device.state(Stamp("vr0/right", k, ns, ns), position, yaw, 1.0 if t >= 1.0 else 0.0)
            log.write(topic, wire.encode(sample), log_time_ns=ns, publish_time_ns=ns)
    config = RetargetedReplayConfig(
        id="vr0", type="replay_retargeted", path=path, topic=topic, robot="arm0", alignment=DEVICE.alignment
    )
    replay = config.build()
    assert isinstance(replay, RetargetedReplay)
    return replay, old, new


def test_retargeted_replay_device_reads_a_recording_and_plays_it_bent(tmp_path: Path) -> None:
    replay, old, new = _retargeted_replay_of_a_recording(tmp_path)
    states, recorded_cube = replay.recorded()
    assert len(states) == 150
    assert np.allclose(recorded_cube.position, old.position)
    got: list[ControllerState] = []
    replay.start(lambda s: got.append(s) if isinstance(s, ControllerState) else None)
    try:
        time.sleep(0.1)
        held = len(got)
        assert held > 0  # holding the first sample until the new cube is seen at rest
        assert np.allclose(got[-1].position, states[0].position)
        replay.observe(
            Pose(Stamp("arm0/cube", 0, 0, 0), np.array([math.nan, 0, 0]), new.orientation, "world")
        )
        assert replay.ignored == 1
        for i in range(30):
            replay.observe(Pose(Stamp("arm0/cube", i, i, i), new.position, new.orientation, "world"))
            time.sleep(0.005)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not any(s.trigger > 0.5 for s in got):
            time.sleep(0.02)
    finally:
        replay.stop()
    grasp = next(s for s in got if s.trigger > 0.5)
    first_closed = next(s for s in states if s.trigger > 0.5)
    shift = FRAME.to_operator(new.position) - FRAME.to_operator(old.position)
    assert np.allclose(grasp.position - first_closed.position, shift, atol=1e-9)
    seqs = [s.stamp.seq for s in got]
    assert seqs == list(range(len(seqs)))


def test_a_late_retargeted_replay_keeps_the_recordings_spacing(tmp_path: Path) -> None:
    """A sink that blocks for 0.2 s at the grasp makes the replay late; the samples it then owes go
    out back to back, each stamped with its due time, 10 ms apart as recorded."""
    replay, _, new = _retargeted_replay_of_a_recording(tmp_path)
    got: list[ControllerState] = []
    at: list[float] = []

    def sink(s: Sample) -> None:
        if not isinstance(s, ControllerState):
            return
        got.append(s)
        at.append(time.perf_counter())
        if s.trigger > 0.5 and sum(g.trigger > 0.5 for g in got) == 1:
            time.sleep(0.2)

    replay.start(sink)
    try:
        for i in range(30):
            replay.observe(Pose(Stamp("arm0/cube", i, i, i), new.position, new.orientation, "world"))
            time.sleep(0.005)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and sum(s.trigger > 0.5 for s in got) < 40:
            time.sleep(0.02)
    finally:
        replay.stop()
    grasp = next(i for i, s in enumerate(got) if s.trigger > 0.5)
    assert at[grasp + 10] - at[grasp + 1] < 0.05  # late: the owed samples went out together
    steps_ms = np.diff([s.stamp.capture_ns for s in got[grasp : grasp + 40]]) / 1e6
    np.testing.assert_allclose(steps_ms, 10.0, atol=0.5)
