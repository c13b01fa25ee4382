"""The C tyre/powertrain callback computes exactly what its Python port says it does."""

from __future__ import annotations

import copy

import mujoco
import numpy as np
import pytest

from harness.plant import Sedan, native, reference


def forces_from_c_and_python(plant: Sedan) -> tuple[np.ndarray, np.ndarray]:
    m = plant.model
    data_c, data_py = copy.copy(plant.data), copy.copy(plant.data)
    mujoco.mj_forward(m, data_c)  # runs the installed C callback on the previous qacc
    mujoco.mj_fwdPosition(m, data_py)
    mujoco.mj_fwdVelocity(m, data_py)
    reference.vehicle_control(m, data_py)
    return data_c.qfrc_applied.copy(), data_py.qfrc_applied.copy()


@pytest.mark.parametrize(
    "manoeuvre",
    [
        lambda k: (300.0 * np.sin(k / 20), 0.2),  # throttle while steering hard
        lambda k: (120.0, -9.1 if k > 100 else 0.2),  # brake in a corner: combined slip
        lambda k: (-450.0, 0.0),  # coasting at full lock
    ],
)
def test_c_callback_matches_the_python_port(manoeuvre) -> None:
    plant = Sedan()
    plant.reset(speed_mps=20.0)
    for k in range(150):
        plant.step(manoeuvre(k))
        if k % 30 == 29:
            from_c, from_python = forces_from_c_and_python(plant)
            assert np.abs(from_c).max() > 100.0  # the tyres carry the car
            np.testing.assert_allclose(from_c, from_python, rtol=1e-9, atol=1e-6)


def test_library_is_cached_by_content(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("KOOPMAN_HARNESS_CACHE", str(tmp_path))
    first = native.build_library()
    mtime = first.stat().st_mtime_ns
    assert native.build_library() == first and first.stat().st_mtime_ns == mtime
    assert first.parent == tmp_path and not list(tmp_path.glob("tmp*"))


def test_callback_ignores_models_without_vehicle_parameters(sedan: Sedan) -> None:
    model = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><freejoint/><geom size='0.1'/></body></worldbody></mujoco>"
    )
    data = mujoco.MjData(model)
    data.qfrc_applied[2] = 5.0
    mujoco.mj_step(model, data, nstep=10)
    assert data.qfrc_applied[2] == 5.0  # untouched: not a vehicle
