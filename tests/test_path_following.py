"""controller.reference=path: the car steers by where it is on a path, not by a state history.

The path QP's prediction is built from the states QP's by running sums; here it is checked
against the plain formulation (the model's lifted state extended by the two error states and
rolled out step by step), and in closed loop on a car that is its own model: it follows a lane
change even when the state reference says "drive straight", which state tracking cannot.
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers import BicycleMPCConfig, DEMPCConfig
from controllers.condensing import time_invariant_theta
from controllers.path_following import FrenetOutputs
from harness.core.episode import MinMaxNormalizer
from harness.references import DoubleLaneChange, ReferencePath
from tests.test_single_track import drives, known_model
from tests.toy_models import toy_linear_model


def test_a_circle_has_the_curvature_and_errors_of_a_circle() -> None:
    angle = np.linspace(0.0, np.pi, 2000)
    radius = 50.0
    path = ReferencePath.from_points(radius * np.sin(angle), radius * (1 - np.cos(angle)))
    inner = slice(5, -5)  # finite differences are one-sided at the ends
    np.testing.assert_allclose(path.curvature_per_m[inner], 1 / radius, rtol=1e-4)
    # A car 0.5 m outside the (left-turning) circle is to the right of it, heading 0.1 rad left.
    k = 700
    heading = path.heading_rad[k]
    outside = np.array(
        [
            path.x_m[k] + 0.5 * np.sin(heading),
            path.y_m[k] - 0.5 * np.cos(heading),
            heading + 0.1,
        ]
    )
    where = path.locate(outside)
    assert where.lateral_error_m == pytest.approx(-0.5, abs=1e-3)
    assert where.heading_error_rad == pytest.approx(0.1, abs=1e-3)
    assert where.station_m == pytest.approx(path.station_m[k], abs=0.05)
    assert path.locate(outside, hint=where.index) == where


def test_a_path_needs_distinct_points() -> None:
    with pytest.raises(ValueError, match="differ"):
        ReferencePath.from_points(np.array([0.0, 1.0, 1.0]), np.zeros(3))


def _augmented_rollout(
    A: np.ndarray,
    B: np.ndarray,
    C: np.ndarray,
    normalizer: MinMaxNormalizer,
    z: np.ndarray,
    errors: np.ndarray,
    inputs: np.ndarray,
    speed: float,
    curvature: np.ndarray,
    dt: float,
) -> np.ndarray:
    """(Np, 5): the model's lifted state extended by (e_y, e_ψ), stepped one step at a time."""
    out = []
    for k, v in enumerate(inputs):
        vy, r = normalizer.states_inverse(C @ z)[1:]
        errors = errors + dt * np.array([vy + speed * errors[1], r - speed * curvature[k]])
        z = A @ z + B @ v
        out.append(np.concatenate([C @ z, errors]))
    return np.array(out)


def test_the_path_prediction_equals_the_extended_model_stepped_by_hand() -> None:
    model = toy_linear_model()
    A, B, C = model.A_, model.B_, model.C_
    Np, Nc, dt, speed = 12, 5, 0.01, 21.0
    rng = np.random.default_rng(0)
    z = model.lift(np.array([21.0, 0.3, -0.2]))
    v_prev = np.array([0.55, 0.5])
    dv = 0.01 * rng.standard_normal((Nc, 2))
    curvature = 0.01 * rng.standard_normal(Np)
    lateral, heading = 0.4, -0.03
    theta = time_invariant_theta(A, B, C, Np, Nc)
    free, state = [], z
    for _ in range(Np):
        state = A @ state + B @ v_prev
        free.append(C @ state)
    frenet = FrenetOutputs(model.normalizer_, dt)
    theta_ext, free_ext = frenet.extend(
        theta, np.ravel(free), C @ z, lateral, heading, speed, curvature
    )
    predicted = (free_ext + theta_ext @ dv.ravel()).reshape(Np, 5)
    plan = v_prev + np.cumsum(np.vstack([dv, np.zeros((Np - Nc, 2))]), axis=0)
    by_hand = _augmented_rollout(
        A, B, C, model.normalizer_, z, np.array([lateral, heading]), plan, speed, curvature, dt
    )
    np.testing.assert_allclose(predicted, by_hand, atol=1e-12)


def _follow(config: DEMPCConfig, reference: np.ndarray, path: ReferencePath) -> np.ndarray:
    """(T, 3) poses of the known single-track car, its own model, under ``config``'s MPC."""
    model = known_model()
    model.normalizer_ = MinMaxNormalizer.fit(drives(model, count=1, steps=400))
    controller = config(model, 0.01)
    controller.reset(reference, path=path, u_prev=np.array([0.0, 0.086]))
    x, pose, poses = reference[0].copy(), np.zeros(3), []
    for k in range(len(reference)):
        poses.append(pose.copy())
        u, info = controller.act(x, k * 0.01, pose=pose)
        vx, vy, r = x
        c, s = np.cos(pose[2]), np.sin(pose[2])
        pose = pose + 0.01 * np.array([vx * c - vy * s, vx * s + vy * c, r])
        x = model.predict(x, u[None])[1]
    assert info.follows_path == (config.reference == "path")
    return np.array(poses)


def test_following_the_path_drives_the_lane_change_even_on_a_straight_state_reference() -> None:
    lane_change = DoubleLaneChange(speed_mps=22.2)
    course = lane_change.course()
    path = course.path()
    straight = np.tile([22.2, 0.0, 0.0], (700, 1))  # the states say: no lane change
    followed = _follow(BicycleMPCConfig(reference="path"), straight, path)
    tracked = _follow(BicycleMPCConfig(), straight, path)
    centre, _ = course.centre_at(followed[:, 0])
    on_course = (followed[:, 0] > course.entry_m) & (followed[:, 0] < course.exit_m)
    assert np.abs(followed[on_course, 1] - centre[on_course]).max() < 0.3
    assert np.abs(tracked[:, 1]).max() < 0.05  # state tracking drove straight on


def test_without_a_path_the_path_mode_tracks_states() -> None:
    reference = np.tile([22.2, 0.0, 0.0], (30, 1))
    model = known_model()
    model.normalizer_ = MinMaxNormalizer.fit(drives(model, count=1, steps=400))
    controller = BicycleMPCConfig(reference="path")(model, 0.01)
    controller.reset(reference)
    _, info = controller.act(reference[0], 0.0)  # no pose needed
    assert not info.follows_path
    controller.reset(reference, path=DoubleLaneChange().course().path())
    with pytest.raises(ValueError, match="pose"):
        controller.act(reference[0], 0.0)


def test_without_a_path_a_path_follower_drives_bit_for_bit_as_its_state_twin() -> None:
    """What lets the pipeline drive such twins once (``DEMPCConfig.without_path``): with no path
    the path follower's inputs equal, bit for bit, those of the same settings tracking states."""
    model = known_model()
    model.normalizer_ = MinMaxNormalizer.fit(drives(model, count=1, steps=400))
    t = np.arange(200) * 0.01
    reference = np.c_[20 + np.sin(t), 0.02 * np.sin(2 * t), 0.1 * np.sin(2 * t)]
    follower = BicycleMPCConfig(reference="path", Q_path=(10.0, 0.0, 30.0, 3.0, 30.0))
    assert follower.without_path() == BicycleMPCConfig()
    inputs = []
    for config in (follower, follower.without_path()):
        controller = config(model, 0.01)
        controller.reset(reference)
        x, applied = reference[0].copy(), []
        for k in range(len(reference)):
            u, _ = controller.act(x, k * 0.01)
            applied.append(u)
            x = model.predict(x, u[None])[1]
        inputs.append(np.array(applied))
    np.testing.assert_array_equal(inputs[0], inputs[1])
    assert np.abs(inputs[0][:, 0]).max() > 1.0  # it steered: a comparison of something


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"reference": "route"}, "controller.reference"),
        ({"Q_path": (1.0, 1.0, 1.0)}, "controller.Q_path"),
        ({"Q_path": (1.0, 0.0, 1.0, 0.0, 0.0)}, "not both 0"),
        ({"Q_path": (1.0, -1.0, 1.0, 1.0, 1.0)}, "controller.Q_path"),
    ],
)
def test_bad_path_settings_name_their_key(overrides: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DEMPCConfig(**overrides)  # type: ignore[arg-type]


def test_the_path_kinematics_speed_keeps_its_band_until_the_speed_leaves_it() -> None:
    """v̄ is the speed to 0.25 m/s, but a band is kept until the speed is 0.75 of a band from
    it: a speed wavering at a band's edge (22.12 / 22.13 m/s) rebuilds the path QP once, not
    every step; a real change of speed moves v̄ on, and a new run starts afresh."""
    model = toy_linear_model()
    controller = DEMPCConfig(Np=10, Nc=7, reference="path")(model, 0.01)
    controller.reset(np.full((20, 3), [22.0, 0.0, 0.0]))
    bands = [controller.path.speed_band(v) for v in (22.12, 22.13, 22.12, 22.3, 22.13, 22.05)]
    assert bands == [22.0, 22.0, 22.0, 22.25, 22.25, 22.0]
    controller.reset(np.full((20, 3), [22.0, 0.0, 0.0]))
    assert controller.path.speed_band(22.13) == 22.25  # the nearest band, nothing held
