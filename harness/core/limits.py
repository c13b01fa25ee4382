"""The actuator limits of the harness's interface: what any plant accepts and any controller may
command, in the paper's units. They are data, not the simulator's: learners scale the pedal by
them and controllers clip to them without loading MuJoCo."""

STEER_WHEEL_LIMIT_DEG = 450.0  # steering-wheel angle, either way (deg)
THROTTLE_MAX = 0.2  # pedal >= 0: throttle opening, 0 .. 0.2
BRAKE_MAX_MPA = 9.1  # pedal < 0: brake master-cylinder pressure, -9.1 .. 0 (MPa)
