"""A synthetic human driver: the paper's person at the wheel, reproducible from a seed.

It strings together manoeuvre segments the way a person exploring a car's envelope would:
launches from rest, cruising at chosen speeds (including parking-lot speeds), coasting, gentle
and hard braking to a stop, and on the steering side straight driving, held angles, ramps,
slaloms, lane changes and sustained corners aimed at a lateral acceleration up to the friction
limit. Inputs are rate limited like a person's hands and feet, and there is one signed pedal, so
throttle and brake can never be pressed together. A driver that notices the car sliding (the rear
axle's sideslip beyond ``recovery_sideslip_deg``) straightens the wheel and lifts off until the
rear has gripped again (below ``recovery_exit_sideslip_deg``); if the car spins anyway (sideslip
beyond ``spin_sideslip_deg`` or rolling backwards), the episode ends there. A drive may start
rolling (``speed_mps``): it then cruises on near that speed first instead of launching.

Why the rear axle and the hysteresis: the sideslip at the centre of gravity is not a slide. In a
tight turn at parking-lot speed it is the geometry's, atan(b tan δ / L), 8° at 260° of steering
and walking pace with every tyre gripping; thresholding it, with one threshold to enter and to
leave, made the driver straighten the wheel, see the "slide" end, steer back in and straighten
again: a saw-tooth of about ±30° at several Hz with a flickering pedal (6 % of the frames of the
old ``data=default``). What a person feels is the tail stepping out, the sideslip at the rear
axle (zero in a gripping low-speed turn), and a person who caught a slide waits until it is over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from harness.core.checks import non_negative, require, shown
from harness.core.limits import BRAKE_MAX_MPA, STEER_WHEEL_LIMIT_DEG, THROTTLE_MAX
from harness.plant.params import SedanParams

G = 9.81
LATERAL_MANOEUVRES = ("straight", "hold", "ramp", "slalom", "lane_change", "corner")
LONGITUDINAL_MANOEUVRES = ("cruise", "coast", "brake")


@dataclass(frozen=True)
class DriverKnowledge:
    """What the driver knows of the car before driving it, as a person would.

    The road's peak friction sets how hard corners are taken; the steering ratio turns an
    intended road-wheel angle into a steering-wheel angle. A plant-specific fact the caller
    reads from its plant; the data store hashes it into the dataset key.
    """

    road_friction: float
    steering_ratio: float

    @classmethod
    def of(cls, params: SedanParams) -> DriverKnowledge:
        """What a driver of this sedan variant knows (its road's grip, its steering ratio)."""
        return cls(params.tire.road_friction, params.steering.steering_ratio)


@dataclass
class DriverConfig:
    """How the driver drives (``data.driver`` in ``conf/data/*.yaml``; the schema of that block)."""

    max_speed_mps: float = 33.0
    # Scales how hard corners, holds and slaloms are taken at speed (1 = up to the limit).
    aggressiveness: float = 0.8
    low_speed_probability: float = 0.2  # cruise segments aimed at 2-8 m/s
    segment_duration_s: tuple[float, float] = (1.5, 6.0)
    steer_rate_deg_per_s: float = 360.0
    throttle_rate_per_s: float = 0.5
    brake_rate_mpa_per_s: float = 25.0
    # Share of segments per manoeuvre, in the order of LATERAL_MANOEUVRES / LONGITUDINAL_MANOEUVRES.
    lateral_weights: tuple[float, ...] = (0.15, 0.15, 0.15, 0.2, 0.1, 0.25)
    longitudinal_weights: tuple[float, ...] = (0.6, 0.15, 0.25)
    hard_brake_probability: float = 0.3  # brake segments at 6-9.1 MPa
    stop_probability: float = 0.4  # brake segments that end at standstill
    # Target lateral acceleration of corners as a fraction of mu g, drawn from [low, high].
    corner_grip_fraction: tuple[float, float] = (0.2, 1.2)
    slalom_frequency_hz: tuple[float, float] = (0.15, 1.0)
    max_steer_amplitude_deg: float = 300.0
    steer_noise_deg: float = 1.5  # hand tremor: a slow random wander of the wheel
    initial_steer_deg: float = 90.0  # the paper's random initial steering-wheel angle, +-
    recovery_sideslip_deg: float = 8.0  # the rear axle's sideslip that starts a recovery
    recovery_exit_sideslip_deg: float = 3.0  # ... and the one below which it ends (hysteresis)
    spin_sideslip_deg: float = 25.0  # at the centre of gravity: the drive ends there

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, list):  # the schema hands sequences over as lists
                value = tuple(value)
                setattr(self, f.name, value)
            for number in value if isinstance(value, tuple) else (value,):
                non_negative(f"data.driver.{f.name}", number)
        for name, count in (("lateral_weights", 6), ("longitudinal_weights", 3)):
            weights = getattr(self, name)
            require(
                len(weights) == count and sum(weights) > 0,
                f"data.driver.{name}",
                f"{count} weights with a positive sum",
                list(weights),
            )
        for name in ("segment_duration_s", "corner_grip_fraction", "slalom_frequency_hz"):
            bounds = getattr(self, name)
            require(
                len(bounds) == 2 and 0 < bounds[0] <= bounds[1],
                f"data.driver.{name}",
                "[low, high] with 0 < low <= high",
                list(bounds),
            )
        require(self.max_speed_mps > 3, "data.driver.max_speed_mps", "> 3", self.max_speed_mps)
        require(
            self.recovery_exit_sideslip_deg < self.recovery_sideslip_deg,
            "data.driver.recovery_exit_sideslip_deg",
            f"below data.driver.recovery_sideslip_deg ({shown(self.recovery_sideslip_deg)})",
            self.recovery_exit_sideslip_deg,
        )


class SyntheticDriver:
    """Closed-loop driver policy ``(t, x) -> (steer_wheel_deg, pedal)`` for one episode."""

    def __init__(
        self,
        config: DriverConfig,
        rng: np.random.Generator,
        dt: float,
        *,
        road_friction: float,
        wheelbase_m: float = 2.7,
        steering_ratio: float = 16.0,
        understeer_rad_per_mps2: float = 0.0045,
        speed_mps: float = 0.0,
    ) -> None:
        """``speed_mps``: the speed the drive starts at (0: from rest, with a launch)."""
        self.config, self.rng, self.dt = config, rng, dt
        self.mu, self.wheelbase, self.ratio = road_friction, wheelbase_m, steering_ratio
        # Where the driver feels a slide: the rear axle, taken half a wheelbase behind the CG.
        self.rear_axle_m = wheelbase_m / 2
        self.understeer = understeer_rad_per_mps2
        self._lateral_p = np.asarray(config.lateral_weights) / sum(config.lateral_weights)
        self._longitudinal_p = np.asarray(config.longitudinal_weights) / sum(
            config.longitudinal_weights
        )
        initial = config.initial_steer_deg
        if speed_mps >= 8.0:  # rolling fast: no more than a held angle the driver would dare
            initial = min(initial, self._dare_hold(speed_mps))
        self.steer = float(rng.uniform(-1, 1) * initial)
        self.pedal = 0.0
        self.noise = 0.0
        self.spun = False
        self.recovering = False
        self._longitudinal_end = self._lateral_end = -1.0
        self._launch = True  # the first feet segment: a launch from rest, or cruising on

    def _dare_hold(self, speed: float) -> float:
        """The largest steering-wheel angle the driver holds at ``speed`` (large when slow)."""
        dare = 2500.0 * self.config.aggressiveness / max(speed, 1.0) ** 1.2
        return (
            self.config.max_steer_amplitude_deg
            if speed < 8
            else min(self.config.max_steer_amplitude_deg, dare)
        )

    # --- segment choice -------------------------------------------------------------------
    def _new_longitudinal(self, t: float, x: np.ndarray) -> None:
        """Feet: a launch first, then cruise / coast / brake segments on their own clock."""
        cfg, rng = self.config, self.rng
        speed = max(x[0], 0.0)
        launch = self._launch
        if self._launch:
            longitudinal, self._launch = "cruise", False
        else:
            longitudinal = LONGITUDINAL_MANOEUVRES[rng.choice(3, p=self._longitudinal_p)]
            if longitudinal == "brake" and speed < 2.0:
                longitudinal = "cruise"  # nothing to brake from: drive off instead
        self.longitudinal = longitudinal
        self._reached_at: float | None = None
        self._longitudinal_end = math.inf  # cruise and brake end once their speed is reached
        if longitudinal == "cruise":
            low = rng.random() < cfg.low_speed_probability
            high = cfg.max_speed_mps
            self.target_speed = rng.uniform(2.0, 8.0) if low else rng.uniform(8.0, high)
            if launch and speed > 3.0:  # a rolling start: cruise on near the speed it has
                self.target_speed = min(speed * rng.uniform(0.85, 1.15), high)
            self.hold_s = rng.uniform(*cfg.segment_duration_s) * 2.0
            # A person rarely holds the pedal for more than ~20 s before doing something else.
            self._longitudinal_end = t + rng.uniform(8.0, 25.0)
        elif longitudinal == "coast":
            self._longitudinal_end = t + rng.uniform(*cfg.segment_duration_s)
        else:
            hard = rng.random() < cfg.hard_brake_probability
            self.brake_mpa = rng.uniform(6.0, BRAKE_MAX_MPA) if hard else rng.uniform(0.5, 4.0)
            stop = rng.random() < cfg.stop_probability
            self.target_speed = 0.0 if stop else speed * rng.uniform(0.3, 0.8)
            self.hold_s = rng.uniform(0.5, 2.0)

    def _new_lateral(self, t: float, x: np.ndarray) -> None:
        """Hands: a steering manoeuvre for the next 1.5-6 s, chosen for the current speed."""
        cfg, rng = self.config, self.rng
        speed = max(x[0], 0.0)
        self._t0 = t
        self._lateral_end = t + rng.uniform(*cfg.segment_duration_s)
        self.lateral = LATERAL_MANOEUVRES[rng.choice(6, p=self._lateral_p)]
        if speed < 3.0 and self.lateral == "corner":
            self.lateral = "hold"  # lateral acceleration is meaningless at walking pace
        sign = rng.choice((-1.0, 1.0))
        amplitude = cfg.max_steer_amplitude_deg
        if self.lateral == "straight":
            self.steer_target = rng.uniform(-10.0, 10.0)
        elif self.lateral == "hold":
            # Large angles at low speed, small ones at speed: what a person would dare.
            self.steer_target = sign * rng.uniform(0.0, self._dare_hold(speed))
        elif self.lateral == "ramp":
            self.ramp_rate = sign * rng.uniform(5.0, 60.0)
        elif self.lateral in ("slalom", "lane_change"):
            self.frequency = rng.uniform(*cfg.slalom_frequency_hz)
            dare = 4000.0 * cfg.aggressiveness / max(speed, 1.0) ** 1.3
            speed_limit = amplitude if speed < 8 else dare
            self.amplitude = sign * rng.uniform(10.0, max(min(amplitude, speed_limit), 15.0))
            if self.lateral == "lane_change":
                self._lateral_end = t + 1.0 / self.frequency
        elif self.lateral == "corner":
            low, high = cfg.corner_grip_fraction
            self.grip_fraction = sign * rng.uniform(low, max(low, high * cfg.aggressiveness))

    # --- the two feet and the hands --------------------------------------------------------
    def _steer_target(self, t: float, x: np.ndarray) -> float:
        if self.lateral == "ramp":
            return self.steer - self.noise + self.ramp_rate * self.dt
        if self.lateral in ("slalom", "lane_change"):
            return self.amplitude * math.sin(2 * math.pi * self.frequency * (t - self._t0))
        if self.lateral == "corner":
            speed = max(x[0], 3.0)
            lateral_accel = self.grip_fraction * self.mu * G
            # Steady-state cornering: delta = (L + K v^2) a_y / v^2 (understeer gradient K).
            delta = (self.wheelbase + self.understeer * speed**2) * lateral_accel / speed**2
            return math.degrees(delta) * self.ratio
        return self.steer_target

    def _pedal_target(self, t: float, x: np.ndarray) -> float:
        speed = x[0]
        if self.longitudinal == "coast":
            return 0.0
        if self.longitudinal == "brake":
            if self._reached_at is None and speed > max(self.target_speed, 0.2):
                return -self.brake_mpa
            if self._reached_at is None:
                self._reached_at = t
            if self.target_speed == 0.0 and t - self._reached_at < self.hold_s:
                return -min(self.brake_mpa, 3.0)  # hold the stopped car a moment
            self._longitudinal_end = t  # speed reached: the next segment starts
            return 0.0
        error = self.target_speed - speed
        if self._reached_at is None and abs(error) < 1.0:
            self._reached_at = t
            # Cruise there a while, then move on.
            self._longitudinal_end = min(self._longitudinal_end, t + self.hold_s)
        if error > -0.5:
            return min(0.08 * error + 0.05, THROTTLE_MAX) if error > 0 else 0.02
        return max(0.6 * error, -2.0)  # gentle braking to come down to the cruise speed

    def rear_sideslip_deg(self, x: np.ndarray) -> float:
        """The sideslip at the rear axle, (vy - b r) / vx: what a slide feels like from the seat
        (zero in a gripping turn at any steering angle, unlike the sideslip at the CG)."""
        return math.degrees(math.atan2(x[1] - self.rear_axle_m * x[2], max(abs(x[0]), 1.0)))

    def spinning(self, x: np.ndarray) -> bool:
        """The car has spun (sideslip beyond ``spin_sideslip_deg``) or rolls backwards: the
        drive ends here (``drive_episode`` keeps it up to this frame)."""
        sideslip = math.degrees(math.atan2(x[1], max(abs(x[0]), 1.0)))
        return abs(sideslip) > self.config.spin_sideslip_deg or x[0] < -0.5

    def __call__(self, t: float, x: np.ndarray) -> tuple[float, float]:
        cfg = self.config
        if t >= self._longitudinal_end:
            self._new_longitudinal(t, x)
        if t >= self._lateral_end:
            self._new_lateral(t, x)
        speed = x[0]
        self.spun = self.spun or self.spinning(x)
        rear_slip = abs(self.rear_sideslip_deg(x))
        if speed <= 3.0 or rear_slip < cfg.recovery_exit_sideslip_deg:
            self.recovering = False
        elif rear_slip > cfg.recovery_sideslip_deg:
            self.recovering = True
        recovering = self.recovering
        steer_target = 0.0 if recovering else self._steer_target(t, x)
        pedal_target = 0.0 if recovering else self._pedal_target(t, x)

        # Hand tremor: an Ornstein-Uhlenbeck wander with a ~1 s correlation time.
        self.noise += (
            -self.noise * self.dt
            + cfg.steer_noise_deg * math.sqrt(2 * self.dt) * self.rng.standard_normal()
        )
        step = cfg.steer_rate_deg_per_s * self.dt * (2.0 if recovering else 1.0)
        self.steer += min(max(steer_target + self.noise - self.steer, -step), step)
        self.steer = min(max(self.steer, -STEER_WHEEL_LIMIT_DEG), STEER_WHEEL_LIMIT_DEG)
        if self.lateral == "ramp" and abs(self.steer) >= cfg.max_steer_amplitude_deg:
            self.ramp_rate = -self.ramp_rate

        # Feet: throttle and brake move at their own rates; the pedal passes through zero.
        throttling = self.pedal > 0 or pedal_target > 0
        rate = cfg.throttle_rate_per_s if throttling else cfg.brake_rate_mpa_per_s
        if self.pedal > 0 and pedal_target < 0:
            pedal_target, rate = 0.0, cfg.throttle_rate_per_s * 4  # lift off first
        step = rate * self.dt
        self.pedal += min(max(pedal_target - self.pedal, -step), step)
        self.pedal = min(max(self.pedal, -BRAKE_MAX_MPA), THROTTLE_MAX)
        return self.steer, self.pedal
