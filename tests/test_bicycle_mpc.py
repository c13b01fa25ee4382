"""controller=bicycle_mpc steers into a lane change on its own (accurate) single-track model.

The reference's lateral velocity is the steady-state sideslip, vy = -1.3 r at 80 km/h, but in
the first 0.1 s (DE-MPC's horizon) steering moves vy the same way as r (the front tyre's force
pushes the centre of gravity before the sideslip builds up). With vy weighted as much as r the
QP traded one error against the other and did not steer (docs/findings/lane_change.md, "The physics
baseline").
"""

from __future__ import annotations

import numpy as np
from hydra.utils import instantiate

from controllers import BicycleMPCConfig
from harness.core.episode import MinMaxNormalizer
from tests.helpers import compose
from tests.test_single_track import drives, known_model


def test_the_baseline_steers_towards_a_negative_yaw_rate_reference() -> None:
    model = known_model()
    model.normalizer_ = MinMaxNormalizer.fit(drives(model, count=1, steps=400))
    yaw_rate = -0.25
    reference = np.tile([22.2, -1.3 * yaw_rate, yaw_rate], (60, 1))
    controller = BicycleMPCConfig()(model, 0.01)
    controller.reset(reference, u_prev=np.array([0.0, 0.086]))
    x = np.array([22.2, 0.0, 0.0])
    steering = []
    for k in range(40):  # the model is the plant: a perfect model, 0.4 s
        u, _ = controller.act(x, k * 0.01)
        steering.append(u[0])
        x = model.predict(x, u[None])[1]
    assert max(steering) <= 0.0  # never the wrong way
    assert min(steering) < -40.0  # 2.25° per step: the rate limit, most of the way
    assert x[2] < 0.5 * yaw_rate  # and the yaw rate follows


def test_the_pipelines_controllers_all_weigh_vy_as_the_dataclass() -> None:
    """The pipeline builds every controller from its YAML: the baseline and the learners' DE-MPC
    weigh the states alike (a fair comparison), vy at 1 %."""
    for name in ("bicycle_mpc", "bicycle_mpc_long", "de_mpc", "de_mpc_long"):
        config = instantiate(compose(f"controller={name}").controller)
        np.testing.assert_array_equal(config.weights()[0], BicycleMPCConfig().weights()[0])
        assert config.weights()[0][1, 1] < 0.1 * config.weights()[0][2, 2]
