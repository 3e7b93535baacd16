"""The hand vector optimizer and retargeter: recovery, limits, mimic joints, warm start, confidence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.devices.glove.kinematics import HandModel
from telerig.ir.types import GripperCommand, HandPose, Stamp
from telerig.retarget.hand import HandRetargeter, KeypointVectors, VectorOptimizer, default_vectors
from telerig.robots.models.hands import HAND_MODELS, HandKinematics, load_hand

pytestmark = pytest.mark.sim

_CACHE: dict[tuple[str, str], HandKinematics] = {}


def _hand(name: str, side: str = "right") -> HandKinematics:
    key = (name, side)
    if key not in _CACHE:
        _CACHE[key] = load_hand(name, side)  # type: ignore[arg-type]
    return _CACHE[key]


def _pose(angles: np.ndarray, k: int = 0, conf: np.ndarray | None = None, hand: str = "right") -> HandPose:
    kp = HandModel.default().keypoints(angles, hand)  # type: ignore[arg-type]
    return HandPose(
        Stamp("glove", k, 1000 + k, 2000 + k),
        hand,  # type: ignore[arg-type]
        kp[0],
        np.array([1.0, 0.0, 0.0, 0.0]),
        kp,
        np.ones(21) if conf is None else conf,
        "right_glove",
    )


def _grasp(s: float) -> np.ndarray:
    """Glove joint angles from open (s = 0) to a power grasp (s = 1). Shape (5, 4)."""
    closed = np.array([[-0.2, 0.6, 0.7, 0.5]] + [[0.0, 1.5, 1.7, 0.9]] * 4)
    return s * closed


@pytest.mark.parametrize("name", HAND_MODELS)
def test_a_pose_of_the_robot_itself_is_recovered(name: str) -> None:
    hand = _hand(name)
    vectors = default_vectors(sorted(hand.keypoints))
    opt = VectorOptimizer(hand, vectors, beta=0.0, iterations=30)
    rng = np.random.default_rng(7)
    for _ in range(5):
        q_true = hand.lower + rng.uniform(0.1, 0.9, len(hand.actuated)) * (hand.upper - hand.lower)
        start = np.clip(q_true + rng.normal(0.0, 0.15, q_true.shape), hand.lower, hand.upper)
        result = opt.solve(opt.forward(q_true), np.ones(len(vectors)), start)
        assert result.residuals.max() < 1e-6


@pytest.mark.parametrize("name", HAND_MODELS)
def test_jacobian_matches_finite_differences(name: str) -> None:
    hand = _hand(name)
    opt = VectorOptimizer(hand, default_vectors(sorted(hand.keypoints)))
    q = hand.lower + 0.4 * (hand.upper - hand.lower)
    opt.forward(q)
    jac = opt._jacobian()
    eps = 1e-6
    num = np.empty_like(jac)
    for k in range(q.size):
        dq = np.zeros_like(q)
        dq[k] = eps
        num[:, k] = ((opt.forward(q + dq) - opt.forward(q - dq)) / (2 * eps)).ravel()
    np.testing.assert_allclose(jac, num, atol=1e-7)


@pytest.mark.parametrize("name", HAND_MODELS)
def test_solutions_never_leave_the_joint_limits(name: str) -> None:
    hand = _hand(name)
    vectors = default_vectors(sorted(hand.keypoints))
    opt = VectorOptimizer(hand, vectors, beta=0.0, iterations=10)
    rng = np.random.default_rng(3)
    lo, hi = hand.model.jnt_range[:, 0], hand.model.jnt_range[:, 1]
    q = hand.neutral()
    for _ in range(20):  # targets far out of reach pull every joint against its bounds
        result = opt.solve(rng.normal(0.0, 0.3, (len(vectors), 3)), np.ones(len(vectors)), q)
        q = result.q
        assert np.all(q >= hand.lower)
        assert np.all(q <= hand.upper)
        full = hand.full(q)
        assert np.all(full >= lo - 1e-12)
        assert np.all(full <= hi + 1e-12)


def test_commanding_all_joints_honours_the_mimic_couplings() -> None:
    hand = _hand("inspire")
    retargeter = HandRetargeter(hand, command="all")
    result = retargeter(_pose(_grasp(0.7)))
    assert result is not None
    cmd = dict(zip(result.command.names, result.command.positions, strict=True))
    assert result.command.names == hand.joint_names
    for finger in ("index", "middle", "ring", "pinky"):
        assert cmd[f"joint_r_{finger}_distal"] == pytest.approx(
            1.06399 * cmd[f"joint_r_{finger}_proximal"] - 0.04545
        )
    assert cmd["joint_r_thumb_middle"] == pytest.approx(1.334 * cmd["joint_r_thumb_proximal_2"])


def test_command_is_stamped_with_the_sample_and_names_the_motors() -> None:
    hand = _hand("ability")
    sample = _pose(_grasp(0.5), k=42)
    result = HandRetargeter(hand)(sample)
    assert result is not None
    assert result.command.stamp == sample.stamp
    assert result.command.names == hand.actuated
    assert result.error_m == pytest.approx(float(np.mean(result.vector_errors)))


@pytest.mark.parametrize("name", HAND_MODELS)
def test_closing_the_human_hand_closes_the_robot_hand(name: str) -> None:
    hand = _hand(name)
    retargeter = HandRetargeter(hand)
    opened = retargeter(_pose(_grasp(0.0)))
    for k in range(1, 11):
        closed = retargeter(_pose(_grasp(k / 10), k))
    assert opened is not None
    assert closed is not None
    tips_open = hand.keypoint_positions(opened.command.positions, (8, 12))
    tips_closed = hand.keypoint_positions(closed.command.positions, (8, 12))
    assert np.all(np.linalg.norm(tips_closed, axis=1) < np.linalg.norm(tips_open, axis=1) - 0.03)
    assert closed.error_m < 0.03


def test_warm_start_is_stable_on_a_held_pose() -> None:
    retargeter = HandRetargeter(_hand("allegro"))
    sample = _pose(_grasp(0.4))
    qs = []
    for _ in range(30):
        result = retargeter(sample)
        assert result is not None
        qs.append(result.command.positions)
    steps = np.abs(np.diff(qs, axis=0)).max(axis=1)
    assert steps[-10:].max() < 1e-4  # settled, no chatter
    assert np.all(np.diff(steps[:5]) <= 1e-9)  # converging monotonically


def test_smoothing_limits_the_jump_per_frame() -> None:
    hand = _hand("inspire")
    jumps = []
    for beta in (1e-4, 1e-1):
        retargeter = HandRetargeter(hand, beta=beta, iterations=1)
        a = retargeter(_pose(_grasp(0.0)))
        b = retargeter(_pose(_grasp(1.0), 1))
        assert a is not None
        assert b is not None
        jumps.append(float(np.abs(b.command.positions - a.command.positions).max()))
    assert jumps[1] < 0.5 * jumps[0]


def test_low_confidence_finger_holds_its_joints() -> None:
    hand = _hand("inspire")
    retargeter = HandRetargeter(hand)
    for k in range(5):
        before = retargeter(_pose(_grasp(0.0), k))
    assert before is not None
    conf = np.ones(21)
    conf[5:9] = 0.1  # index finger lost
    after = retargeter(_pose(_grasp(1.0), 9, conf))
    assert after is not None
    assert not after.valid[1]
    assert math.isnan(after.vector_errors[1])
    index = hand.actuated.index("joint_r_index_proximal")
    middle = hand.actuated.index("joint_r_middle_proximal")
    assert after.command.positions[index] == pytest.approx(before.command.positions[index], abs=1e-6)
    assert after.command.positions[middle] > before.command.positions[middle] + 0.5


def test_no_usable_vector_yields_none() -> None:
    retargeter = HandRetargeter(_hand("inspire"))
    conf = np.ones(21)
    conf[[2, 4, 8, 12, 16, 20]] = 0.0
    assert retargeter(_pose(_grasp(0.5), conf=conf)) is None
    assert retargeter(_pose(_grasp(0.5), hand="left")) is None  # the other hand
    assert retargeter(GripperCommand(Stamp("x", 0, 0, 0), 0.5)) is None


def test_non_finite_keypoints_are_skipped() -> None:
    kp = HandModel.default().keypoints(_grasp(0.3), "right")
    kp[12] = np.nan
    sample = HandPose(Stamp("cam", 0, 0, 0), "right", kp[0], np.array([1.0, 0, 0, 0]), kp, np.ones(21), "op")
    result = HandRetargeter(_hand("ability"))(sample)
    assert result is not None
    assert not result.valid[2]
    assert np.all(np.isfinite(result.command.positions))


def test_per_finger_scale_applies_to_its_vectors() -> None:
    retargeter = HandRetargeter(_hand("ability"), scale=1.0, finger_scales=(2.0, 1.0, 1.0, 1.0, 0.5))
    np.testing.assert_allclose(retargeter.alpha, [2.0, 1.0, 1.0, 1.0, 0.5, 2.0])


def test_vectors_the_robot_cannot_show_are_rejected() -> None:
    with pytest.raises(ValueError, match=r"no point for keypoint\(s\) \[20\]"):
        VectorOptimizer(_hand("allegro"), KeypointVectors.of([(0, 20)]))
    with pytest.raises(ValueError, match="finger_scales"):
        HandRetargeter(_hand("allegro"), finger_scales=(1.0, 1.0))


def _box_qps(opt: VectorOptimizer, n: int, seed: int):  # type: ignore[no-untyped-def]
    """Random box-constrained quadratic models like a solve builds: H SPD, q in the box (a third of
    the joints on a bound), g pulling through the bounds."""
    rng = np.random.default_rng(seed)
    lo, hi = opt._lo, opt._hi
    for _ in range(n):
        a = rng.normal(size=(lo.size, lo.size))
        h = a @ a.T + 1e-3 * np.eye(lo.size)
        q = lo + rng.uniform(0.0, 1.0, lo.size) * (hi - lo)
        on = rng.random(lo.size) < 1 / 3
        q[on] = np.where(rng.random(int(on.sum())) < 0.5, lo[on], hi[on])
        yield q, h, rng.normal(0.0, 5.0, lo.size)


def _model(h: np.ndarray, g: np.ndarray, dq: np.ndarray) -> float:
    return float(0.5 * dq @ h @ dq - g @ dq)


@pytest.mark.parametrize("name", HAND_MODELS)
def test_the_qp_step_is_the_exact_minimizer_within_the_bounds(name: str) -> None:
    opt = VectorOptimizer(_hand(name), default_vectors(sorted(_hand(name).keypoints)))
    lo, hi = opt._lo, opt._hi
    for q, h, g in _box_qps(opt, 25, seed=11):
        step = opt._step(q, h, g)
        assert np.all(step >= lo)
        assert np.all(step <= hi)
        # KKT of min 1/2 dq'H dq - g'dq, lo - q <= dq <= hi - q: the gradient H dq - g is zero on
        # free joints, >= 0 at the lower bound and <= 0 at the upper bound.
        grad = h @ (step - q) - g
        at_lo, at_hi = step <= lo + 1e-9, step >= hi - 1e-9
        free = ~(at_lo | at_hi)
        scale = 1.0 + np.abs(g).max()
        assert np.all(np.abs(grad[free]) < 1e-6 * scale)
        assert np.all(grad[at_lo] > -1e-6 * scale)
        assert np.all(grad[at_hi] < 1e-6 * scale)


def test_a_frame_the_qp_solver_does_not_finish_holds_the_last_solution(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import daqp  # the optimizer calls daqp.solve through the module

    hand = _hand("inspire")
    opt = VectorOptimizer(hand, default_vectors(sorted(hand.keypoints)))
    q_prev = hand.lower + 0.3 * (hand.upper - hand.lower)
    targets = opt.forward(hand.lower + 0.6 * (hand.upper - hand.lower))  # a real pull away from q_prev

    def unfinished(*args: object) -> tuple[np.ndarray, float, int, dict[str, float]]:
        return np.full(q_prev.size, np.nan), np.nan, -4, {}  # daqp's exit flag: iteration limit

    monkeypatch.setattr(daqp, "solve", unfinished)
    result = opt.solve(targets, np.ones(len(opt.vectors)), q_prev)
    np.testing.assert_array_equal(result.q, q_prev)  # never NaN, never a guess: the hand holds
    assert result.iterations == 1
