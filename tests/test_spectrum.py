"""The spectrum against matrices whose eigenvalues are known: counted, named and timed."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from harness.core.contracts import Dynamics, dynamics_of
from harness.core.episode import MinMaxNormalizer
from harness.evaluation.spectrum import plot_spectrum, spectrum, spectrum_figure, state_matrices

NORMALIZER = MinMaxNormalizer(
    np.array([0.0, -2.0, -1.0]),
    np.array([40.0, 2.0, 1.0]),
    np.array([-450.0, -1.0]),
    np.array([450.0, 1.0]),
)


@dataclass
class Linear:
    """z = [x_n; 1; w]: vx grows by 1 % a step, (vy, w) rotate at |λ| = 1.02, yaw rate decays."""

    dynamics: ClassVar[Dynamics] = "linear"

    A_: np.ndarray = field(
        default_factory=lambda: np.block(
            [
                [np.diag([1.01, 0.0, 0.5]), np.zeros((3, 2))],
                [np.zeros((2, 3)), np.eye(2)],
            ]
        )
    )
    B_: np.ndarray = field(default_factory=lambda: np.zeros((5, 2)))
    C_: np.ndarray = field(default_factory=lambda: np.eye(3, 5))
    normalizer_: MinMaxNormalizer = NORMALIZER

    def __post_init__(self) -> None:
        rotation = 1.02 * np.array([[np.cos(0.1), -np.sin(0.1)], [np.sin(0.1), np.cos(0.1)]])
        self.A_[np.ix_([1, 4], [1, 4])] = rotation

    def lift(self, x: np.ndarray) -> np.ndarray:
        raise NotImplementedError


@dataclass
class Bilinear(Linear):
    """Stable at zero input; full steering adds 0.03 to the yaw-rate mode's eigenvalue."""

    dynamics: ClassVar[Dynamics] = "bilinear"

    H_: np.ndarray = field(default_factory=lambda: np.zeros((2, 5, 5)))

    def __post_init__(self) -> None:
        self.A_ = np.diag([0.99, 0.9, 0.98, 1.0, 0.5])
        self.H_[0, 2, 2] = 0.06  # steering (v0 = 0.5): A + (v - 0.5) H at v = 1 adds 0.03

    @property
    def v0_(self) -> np.ndarray:
        return self.normalizer_.inputs(np.zeros(2))


def test_modes_outside_the_unit_circle_are_named_counted_once_and_timed() -> None:
    model = Linear()
    assert dynamics_of(model) == "linear"
    metrics, eigenvalues = spectrum(model, dt=0.01)
    assert set(eigenvalues) == {"A"}
    assert metrics["max_abs_eigenvalue"] == pytest.approx(1.02)
    modes = metrics["unstable_modes"]
    # the complex pair is one mode; the constant's λ = 1 is on the circle, not outside it
    assert [mode["dominant"] for mode in modes] == ["vy", "vx"]
    assert metrics["matrices"]["A"]["unstable"] == 2
    pair, vx = modes
    assert pair["abs"] == pytest.approx(1.02) and pair["eigenvalue"][1] > 0
    assert vx["eigenvalue"] == pytest.approx([1.01, 0.0])
    assert vx["doubling_time_s"] == pytest.approx(math.log(2) * 0.01 / math.log(1.01))
    assert pair["matrix"] == vx["matrix"] == "A"


def test_a_bilinear_model_is_examined_at_zero_input_and_at_the_corners_of_the_input_box() -> None:
    model = Bilinear()
    assert dynamics_of(model) == "bilinear"
    matrices = state_matrices(model)
    assert list(matrices) == [
        "zero input",
        "steer_wheel_deg=min,pedal=min",
        "steer_wheel_deg=min,pedal=max",
        "steer_wheel_deg=max,pedal=min",
        "steer_wheel_deg=max,pedal=max",
    ]
    metrics, _ = spectrum(model, dt=0.01)
    assert metrics["matrices"]["zero input"]["unstable"] == 0
    assert metrics["max_abs_eigenvalue"] == pytest.approx(1.01)
    unstable = {mode["matrix"] for mode in metrics["unstable_modes"]}
    assert unstable == {"steer_wheel_deg=max,pedal=min", "steer_wheel_deg=max,pedal=max"}
    assert {mode["dominant"] for mode in metrics["unstable_modes"]} == {"yaw_rate"}


def test_the_figure_plots_every_matrix_eigenvalues_and_zooms_onto_those_near_one() -> None:
    _, eigenvalues = spectrum(Bilinear(), dt=0.01)
    whole, zoom = spectrum_figure(eigenvalues, title="toy").axes
    circle, *points = whole.get_lines()
    np.testing.assert_allclose(np.hypot(*circle.get_data()), 1.0)  # the unit circle
    assert len(points) == len(eigenvalues)
    for line, (label, values) in zip(points, eigenvalues.items(), strict=True):
        np.testing.assert_array_equal(line.get_data(), (values.real, values.imag))
        assert line.get_label() == f"{label} (max |λ| {np.abs(values).max():.6f})"
    # The zoom holds every eigenvalue within 0.1 of λ = 1 (here 1.01, the furthest) and is
    # centred on 1.
    low, high = zoom.get_xlim()
    assert low < 0.99 and high > 1.01 and (low + high) / 2 == pytest.approx(1.0)
    assert whole.get_title() == "toy"


def test_the_figure_is_written_as_a_png(tmp_path: Path) -> None:
    _, eigenvalues = spectrum(Linear(), dt=0.01)
    path = plot_spectrum(eigenvalues, tmp_path / "nested" / "spectrum.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
