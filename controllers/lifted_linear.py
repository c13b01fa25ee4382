"""A least-squares lifted-linear model and a plant made of a model, for controller checks.

Not a learner (those live in ``learners/``): a fixed polynomial lift and one least-squares
solve (EDMD with hand-picked observables) give, in under a second, a model that satisfies the
controller's contract well enough to close a loop on the plant; ``ModelPlant`` steps a model
as if it were the vehicle, so a controller can be checked against its exact model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from harness.data.episode import Episode, MinMaxNormalizer


def polynomial_features(x_norm: np.ndarray) -> np.ndarray:
    """(..., 10): 1, the six quadratic and three cubic monomials of the centred state.

    The products carry what a linear model misses: vx·r (centripetal), lateral terms growing
    with speed.
    """
    centred = np.asarray(x_norm, dtype=float) - 0.5
    vx, vy, r = centred[..., 0], centred[..., 1], centred[..., 2]
    terms = [np.ones_like(vx), vx * vy, vx * r, vy * r, vx * vx, vy * vy, r * r]
    return np.stack([*terms, vx * vx * vy, vx * vx * r, vx**3], axis=-1)


def constant_feature(x_norm: np.ndarray) -> np.ndarray:
    """(..., 1): the constant observable, enough for an affine (linear in SI units) system."""
    return np.ones((*np.shape(x_norm)[:-1], 1))


@dataclass
class LiftedLinearModel:
    """z = [x_norm; features(x_norm)], z⁺ = A_ z + B_ v, x_norm = C_ z (the DE-MPC contract)."""

    A_: np.ndarray
    B_: np.ndarray
    normalizer_: MinMaxNormalizer
    features: Callable[[np.ndarray], np.ndarray] = field(default=polynomial_features)

    @property
    def C_(self) -> np.ndarray:  # noqa: N802
        size = self.A_.shape[0]
        return np.hstack([np.eye(3), np.zeros((3, size - 3))])

    def lift(self, x_physical: np.ndarray) -> np.ndarray:
        x_norm = self.normalizer_.states(x_physical)
        return np.concatenate([x_norm, self.features(x_norm)], axis=-1)

    def predict(self, x0: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """(T + 1, 3) physical states from x0 under the (T, 2) physical inputs, open loop."""
        z = self.lift(x0)
        v = self.normalizer_.inputs(inputs)
        states = [z]
        for v_k in v:
            z = self.A_ @ z + self.B_ @ v_k
            states.append(z)
        return self.normalizer_.states_inverse(np.array(states) @ self.C_.T)


def fit_lifted_linear(
    episodes: Sequence[Episode],
    features: Callable[[np.ndarray], np.ndarray] = polynomial_features,
    normalizer: MinMaxNormalizer | None = None,
) -> LiftedLinearModel:
    """Least squares [A B] = argmin Σ ||z_{k+1} - A z_k - B v_k||² over all one-step pairs."""
    normalizer = normalizer or MinMaxNormalizer.fit(episodes)
    before, after, inputs = [], [], []
    for episode in episodes:
        x_norm = normalizer.states(episode.states)
        z = np.concatenate([x_norm, features(x_norm)], axis=-1)
        before.append(z[:-1])
        after.append(z[1:])
        inputs.append(normalizer.inputs(episode.inputs[:-1]))
    regressors = np.hstack([np.concatenate(before), np.concatenate(inputs)])
    solution, *_ = np.linalg.lstsq(regressors, np.concatenate(after), rcond=None)
    size = before[0].shape[1]
    return LiftedLinearModel(solution[:size].T, solution[size:].T, normalizer, features)


def toy_linear_model() -> LiftedLinearModel:
    """An exact lifted-linear system, z = [x_norm; 1], at rest at (20 m/s, 0, 0) under u = 0.

    Pedal drives vx, steering drives the coupled (vy, yaw_rate) pair; stable, well damped.
    """
    normalizer = MinMaxNormalizer(
        np.array([0.0, -2.0, -1.0]),
        np.array([40.0, 2.0, 1.0]),
        np.array([-450.0, -1.0]),
        np.array([450.0, 1.0]),
    )
    a = np.array([[0.995, 0.0, 0.0], [0.0, 0.90, 0.04], [0.0, 0.03, 0.93]])
    b = np.array([[0.0, 0.004], [0.02, 0.0], [0.03, 0.0]])
    x_rest, v_rest = np.full(3, 0.5), np.full(2, 0.5)
    A = np.eye(4)  # noqa: N806
    A[:3, :3], A[:3, 3] = a, x_rest - a @ x_rest - b @ v_rest
    B = np.vstack([b, np.zeros((1, 2))])  # noqa: N806
    return LiftedLinearModel(A, B, normalizer, constant_feature)


def feasible_reference(model: LiftedLinearModel, steps: int = 600) -> np.ndarray:
    """(steps, 3) states the model itself reaches from (20 m/s, 0, 0) under slow inputs."""
    plant = ModelPlant(model, x0=np.array([20.0, 0.0, 0.0]))
    t = np.arange(steps) * plant.dt
    inputs = np.stack([60 * np.sin(2 * np.pi * 0.4 * t), 0.05 * np.sin(2 * np.pi * 0.2 * t)], 1)
    states = [plant.reset()]
    states += [plant.step(u) for u in inputs[:-1]]
    return np.array(states)


class ModelPlant:
    """A plant whose dynamics are a lifted-linear model: the controller's model is exact.

    Only consistent when the lift is closed under the dynamics (e.g. ``constant_feature``): the
    state is x = normalizer⁻¹(C z) and the next z is A z + B v.
    """

    dt = 0.01
    state_names = ("vx", "vy", "yaw_rate")
    input_names = ("steer_wheel_deg", "pedal")

    def __init__(self, model: LiftedLinearModel, x0: np.ndarray | None = None) -> None:
        self.model = model
        self.x0 = np.zeros(3) if x0 is None else np.asarray(x0, dtype=float)
        self.reset()

    def reset(self, seed: int | None = None, speed_mps: float = 0.0) -> np.ndarray:
        del seed
        x = self.x0.copy()
        if speed_mps:
            x[0] = speed_mps
        self._z = self.model.lift(x)
        self.pose = np.zeros(3)
        return self.state

    def step(self, u: np.ndarray) -> np.ndarray:
        vx, vy, yaw_rate = self.state
        self._z = self.model.A_ @ self._z + self.model.B_ @ self.model.normalizer_.inputs(u)
        # Pose (X, Y, yaw) by planar kinematics, for display only.
        yaw = self.pose[2]
        self.pose = self.pose + self.dt * np.array(
            [vx * np.cos(yaw) - vy * np.sin(yaw), vx * np.sin(yaw) + vy * np.cos(yaw), yaw_rate]
        )
        return self.state

    @property
    def state(self) -> np.ndarray:
        return self.model.normalizer_.states_inverse(self.model.C_ @ self._z)
