"""Standard vehicle-dynamics tests on the plant: would an engineer recognise a sedan?

Each test is one closed-loop rollout with a simple test driver; every rollout is recorded.
Metrics (SI unless the key says otherwise) go under ``characterize`` in ``metrics.json``:

- ``understeer_gradient_deg_per_g``: ISO 4138 constant-speed method, slow steering ramp;
  K = d(delta)/d(a_y) - L / v^2 on the linear range (a_y in [0.5, 4] m/s^2) of the rising
  branch (before a_y first reaches the top of that range), road-wheel angle
  delta = steering-wheel angle / ratio.
- ``understeer_gradient_steady_state_deg_per_g``: the same K by ISO 4138's steady-state
  method: several steering-wheel angles, each held at constant speed until steady, one point
  (a_y, delta - L r / v) per angle, fitted on the same range; ``steady_state`` holds every point
  and, per speed, K and the yaw-rate gain relative to kinematic (r / (v delta / L)) at the
  smallest angle. The two methods agree within a few per cent (a test holds them to 10 %).
- ``max_lateral_accel_mps2``: peak of a_y (0.5 s moving average) on that ramp.
- ``yaw_rate_rise_time_s`` / ``yaw_rate_overshoot``: ISO 7401 step steer at 80 km/h sized for
  4 m/s^2; rise time is ISO's response time, from 50 % steering input to 90 % of the steady yaw
  rate; overshoot is peak / steady yaw rate (1.0 = none).
- ``braking_distance_100kph_m``: full brake pressure (9.1 MPa) from 100 km/h to standstill.
- ``accel_0_100kph_s`` (null when throttle 0.2 never reaches 100 km/h) and ``top_speed_mps``.
- ``kinematic_yaw_rate_error``: |r - v delta / L| / (v delta / L) at 3 m/s.
- ``drag_coefficient_fit`` / ``rolling_resistance_fit``: coast-down (SAE J2263 style) fit of
  F = A + B v + C v^2, with Cd = 2 C / (rho A_front) and Cr = A / (m g).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from harness.core.checks import positive, require, shown
from harness.output import save_figure
from harness.plant import Sedan
from harness.plant.rollout import SpeedHold, Trajectory, simulate
from harness.recorder import Recorder

G = 9.81
KPH_100 = 100 / 3.6


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average; near the ends it averages the samples that exist (no zero
    padding, which once pulled a spinning car's last samples into the linear range)."""
    if window <= 1:
        return values
    kernel = np.ones(window)
    total = np.convolve(values, kernel, mode="same")
    count = np.convolve(np.ones_like(values), kernel, mode="same")
    return total / count


def understeer_gradient(lateral: np.ndarray, excess: np.ndarray, upper: float) -> float:
    """K (rad per m/s^2) = slope of delta - L r / v against a_y on the linear range (0.5, upper);
    NaN with fewer than 3 points there."""
    linear = (lateral > 0.5) & (lateral < upper)
    if linear.sum() < 3:
        return float("nan")
    return float(np.polyfit(lateral[linear], excess[linear], 1)[0])


@dataclass
class Characterize:
    """Runs the standard tests; the fields are the schema of ``conf/task/characterize.yaml``."""

    circle_speed_mps: float = 80 / 3.6  # ISO 4138 constant-speed ramp, ISO 7401 step: 80 km/h
    steer_ramp_deg_per_s: float = 8.0  # slow enough to be quasi-steady
    steer_ramp_max_deg: float = 360.0
    step_target_lateral_accel_mps2: float = 4.0
    step_steer_rate_deg_per_s: float = 400.0
    low_speed_mps: float = 3.0  # kinematic (Ackermann) yaw-rate check
    low_speed_steer_deg: float = 90.0
    coast_start_speed_mps: float = 33.0  # coast-down fit range
    coast_end_speed_mps: float = 5.0
    launch_duration_s: float = 150.0  # full throttle (0.2) from rest
    # ISO 4138 steady-state method: the speeds, and the steering-wheel angles held at each for
    # steady_state_hold_s (the last 1 s averaged).
    steady_state_speeds_mps: tuple[float, ...] = (10.0, 20.0, 80 / 3.6, 30.0)
    steady_state_steer_deg: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 60.0)
    steady_state_hold_s: float = 5.0

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.type == "float":
                positive(f"task.{f.name}", getattr(self, f.name))
        speeds = tuple(
            positive("task.steady_state_speeds_mps", v) for v in self.steady_state_speeds_mps
        )
        steers = tuple(
            positive("task.steady_state_steer_deg", a) for a in self.steady_state_steer_deg
        )
        require(len(speeds) >= 1, "task.steady_state_speeds_mps", "a non-empty list", speeds)
        require(len(steers) >= 3, "task.steady_state_steer_deg", ">= 3 steering angles", steers)
        self.steady_state_speeds_mps, self.steady_state_steer_deg = speeds, steers
        require(
            self.steady_state_hold_s >= 2.0,
            "task.steady_state_hold_s",
            ">= 2 s",
            self.steady_state_hold_s,
        )
        require(
            self.coast_end_speed_mps < self.coast_start_speed_mps,
            "task.coast_end_speed_mps",
            f"< task.coast_start_speed_mps ({shown(self.coast_start_speed_mps)})",
            self.coast_end_speed_mps,
        )

    def __call__(self, plant: Sedan, recorder: Recorder, output_dir: Path) -> dict[str, dict]:
        runs: dict[str, Trajectory] = {}
        metrics: dict[str, Any] = {}
        for test in (
            self.steady_state_circle,
            self.steady_state_holds,
            self.step_steer,
            self.braking,
            self.launch,
            self.low_speed_turn,
            self.coast_down,
        ):
            name, trajectories, result = test(plant, metrics)
            if isinstance(trajectories, Trajectory):
                trajectories = {name: trajectories}
            metrics.update(result)
            for run_name, trajectory in trajectories.items():
                runs[run_name] = trajectory
                recorder.rollout(
                    f"characterize/{run_name}",
                    trajectory.time_s,
                    trajectory.states,
                    trajectory.inputs,
                    trajectory.poses,
                    extra={"lateral_accel_mps2": trajectory.lateral_accel_mps2},
                )
        metrics["road_friction"] = plant.params.tire.road_friction
        metrics["total_mass_kg"] = float(plant.model.body_subtreemass[1])
        metrics["clipped_inputs"] = plant.clipped_inputs
        plot(runs, metrics, plant, output_dir / "characterize.png")
        return {"characterize": metrics}

    # ISO 4138, constant speed, slowly increasing steering-wheel angle.
    def steady_state_circle(self, plant: Sedan, _: dict) -> tuple[str, Trajectory, dict]:
        hold = SpeedHold(self.circle_speed_mps, plant.dt)
        duration = self.steer_ramp_max_deg / self.steer_ramp_deg_per_s + 2.0
        ramp = self.steer_ramp_deg_per_s

        def policy(t: float, x: np.ndarray) -> tuple[float, float]:
            return (min(max(t - 2.0, 0.0) * ramp, self.steer_ramp_max_deg), hold(x[0]))

        def spun(t: float, x: np.ndarray) -> bool:
            return abs(np.arctan2(x[1], abs(x[0]) + 1e-3)) > np.deg2rad(20) or x[0] < 3.0

        run = simulate(plant, policy, duration, speed_mps=self.circle_speed_mps, stop=spun)
        lateral = moving_average(run.lateral_accel_mps2, int(0.5 / plant.dt))
        delta = np.deg2rad(run.inputs[:, 0]) / plant.params.steering.steering_ratio
        upper = _linear_range_top(plant)
        # The rising branch only: past the grip limit a_y falls back through the linear range
        # with the wheel turned far, which is no longer the steady-state relation.
        reached = np.flatnonzero(lateral >= upper)
        rising = (run.time_s > 2.5) & (
            np.arange(len(lateral)) < (reached[0] if reached.size else len(lateral))
        )
        vx = run.states[:, 0]
        # delta - L r / vx isolates the understeer term K a_y without assuming constant speed.
        excess = delta - _wheelbase(plant) * run.states[:, 2] / np.maximum(vx, 1.0)
        gradient = understeer_gradient(lateral[rising], excess[rising], upper)
        self._ramp = (run.inputs[:, 0], lateral)
        return (
            "steady_state_circle",
            run,
            {
                "understeer_gradient_deg_per_g": float(np.rad2deg(gradient) * G),
                "max_lateral_accel_mps2": float(np.nanmax(lateral[run.time_s > 2.5])),
            },
        )

    # ISO 4138, constant speed, discrete steering-wheel angles each held until steady.
    def steady_state_holds(
        self, plant: Sedan, _: dict
    ) -> tuple[str, dict[str, Trajectory], dict[str, Any]]:
        ratio = plant.params.steering.steering_ratio
        wheelbase, upper = _wheelbase(plant), _linear_range_top(plant)
        hold_s, angles = self.steady_state_hold_s, self.steady_state_steer_deg
        settle = round(1.0 / plant.dt)  # average the last second of every hold
        runs: dict[str, Trajectory] = {}
        points: list[dict[str, float]] = []
        by_speed: dict[str, dict[str, float]] = {}
        for speed in self.steady_state_speeds_mps:
            hold = SpeedHold(speed, plant.dt)

            def policy(t: float, x: np.ndarray, hold: SpeedHold = hold) -> tuple[float, float]:
                index = min(int(t // hold_s), len(angles) - 1)
                start = angles[index - 1] if index else 0.0
                # Move to the next angle at 100 deg/s, then hold it.
                moved = min((t - index * hold_s) * 100.0, abs(angles[index] - start))
                return (start + np.sign(angles[index] - start) * moved, hold(x[0]))

            def spun(t: float, x: np.ndarray) -> bool:
                return abs(np.arctan2(x[1], abs(x[0]) + 1e-3)) > np.deg2rad(20) or x[0] < 1.0

            run = simulate(plant, policy, hold_s * len(angles), speed_mps=speed, stop=spun)
            runs[f"steady_state_{speed:.1f}mps"] = run
            lateral_ss, excess_ss, gains = [], [], []
            for i, angle in enumerate(angles):
                end = round((i + 1) * hold_s / plant.dt)
                if end > len(run.time_s) - 1:
                    break  # the car spun before this hold ended
                vx, _, yaw_rate = run.states[end - settle : end].mean(axis=0)
                delta = np.deg2rad(angle) / ratio
                lateral_ss.append(vx * yaw_rate)  # a_y = v r in a steady turn
                excess_ss.append(delta - wheelbase * yaw_rate / vx)
                gains.append(yaw_rate / (vx * delta / wheelbase))
                points.append(
                    {
                        "speed_mps": float(vx),
                        "steer_wheel_deg": float(angle),
                        "lateral_accel_mps2": float(vx * yaw_rate),
                        "yaw_rate_radps": float(yaw_rate),
                    }
                )
            gradient = understeer_gradient(np.array(lateral_ss), np.array(excess_ss), upper)
            by_speed[f"{speed:.1f}"] = {
                "understeer_gradient_deg_per_g": float(np.rad2deg(gradient) * G),
                "yaw_rate_gain_ratio": float(gains[0]) if gains else float("nan"),
            }
        circle = by_speed.get(f"{self.circle_speed_mps:.1f}")
        return (
            "steady_state",
            runs,
            {
                "understeer_gradient_steady_state_deg_per_g": (
                    circle["understeer_gradient_deg_per_g"] if circle else None
                ),
                "steady_state": {"by_speed_mps": by_speed, "points": points},
            },
        )

    # ISO 7401 step steer, pedal frozen at the value that held the speed.
    def step_steer(self, plant: Sedan, _: dict) -> tuple[str, Trajectory, dict]:
        steer, lateral = self._ramp
        below = np.nonzero(lateral >= self.step_target_lateral_accel_mps2)[0]
        amplitude = float(steer[below[0]]) if below.size else 0.5 * self.steer_ramp_max_deg
        hold = SpeedHold(self.circle_speed_mps, plant.dt)
        step_start = 2.0
        frozen: list[float] = []
        rate = self.step_steer_rate_deg_per_s

        def policy(t: float, x: np.ndarray) -> tuple[float, float]:
            if t < step_start:
                return (0.0, hold(x[0]))
            if not frozen:
                frozen.append(hold(x[0]))
            return (min((t - step_start) * rate, amplitude), frozen[0])

        run = simulate(plant, policy, step_start + 4.0, speed_mps=self.circle_speed_mps)
        yaw_rate = run.states[:, 2]
        steady = float(np.mean(yaw_rate[run.time_s > step_start + 3.0]))
        half_input = step_start + 0.5 * amplitude / rate
        after = run.time_s >= half_input
        reached = np.nonzero(after & (yaw_rate >= 0.9 * steady))[0]
        rise = float(run.time_s[reached[0]] - half_input) if reached.size else None
        return (
            "step_steer",
            run,
            {
                "yaw_rate_rise_time_s": rise,
                "yaw_rate_overshoot": float(yaw_rate.max() / steady),
                "step_steer_amplitude_deg": amplitude,
                "step_steer_lateral_accel_mps2": float(
                    np.mean(run.lateral_accel_mps2[run.time_s > step_start + 3.0])
                ),
            },
        )

    def braking(self, plant: Sedan, _: dict) -> tuple[str, Trajectory, dict]:
        run = simulate(
            plant,
            lambda t, x: (0.0, Sedan.input_low[1]),
            20.0,
            speed_mps=KPH_100,
            stop=lambda t, x: x[0] < 0.05,
        )
        return (
            "braking",
            run,
            {
                "braking_distance_100kph_m": float(run.distance_m[-1]),
                "braking_mean_decel_mps2": float(KPH_100 / run.time_s[-1]),
            },
        )

    def launch(self, plant: Sedan, _: dict) -> tuple[str, Trajectory, dict]:
        run = simulate(plant, lambda t, x: (0.0, Sedan.input_high[1]), self.launch_duration_s)
        vx = run.states[:, 0]
        reached = np.nonzero(vx >= KPH_100)[0]
        window = int(5.0 / plant.dt)
        still_accelerating = (vx[-1] - vx[-window]) / 5.0 > 0.05
        return (
            "launch",
            run,
            {
                "accel_0_100kph_s": float(run.time_s[reached[0]]) if reached.size else None,
                "top_speed_mps": None if still_accelerating else float(vx[-1]),
                "speed_after_launch_mps": float(vx[-1]),
            },
        )

    def low_speed_turn(self, plant: Sedan, _: dict) -> tuple[str, Trajectory, dict]:
        hold = SpeedHold(self.low_speed_mps, plant.dt)
        steer = self.low_speed_steer_deg
        run = simulate(plant, lambda t, x: (steer, hold(x[0])), 8.0, speed_mps=self.low_speed_mps)
        settled = run.time_s > 5.0
        vx, _, yaw_rate = run.states[settled].T
        delta = np.deg2rad(steer) / plant.params.steering.steering_ratio
        kinematic = vx * delta / _wheelbase(plant)
        error = np.mean(np.abs(yaw_rate - kinematic)) / np.mean(kinematic)
        return ("low_speed_turn", run, {"kinematic_yaw_rate_error": float(error)})

    def coast_down(self, plant: Sedan, _: dict) -> tuple[str, Trajectory, dict]:
        end = self.coast_end_speed_mps
        run = simulate(
            plant,
            lambda t, x: (0.0, 0.0),
            600.0,
            speed_mps=self.coast_start_speed_mps,
            stop=lambda t, x: x[0] < end,
        )
        vx = run.states[:, 0]
        decel = -np.gradient(vx, run.time_s)
        mass = float(plant.model.body_subtreemass[1])
        spin_inertia = sum(
            plant.model.body(f"wheel_{c}").inertia[1]
            + plant.model.dof_armature[plant.model.joint(f"spin_{c}").dofadr[0]]
            for c in ("fl", "fr", "rl", "rr")
        )
        radius = plant._rolling_radius
        force = (mass + spin_inertia / radius**2) * decel
        use = (run.time_s > 1.0) & (vx > end + 1.0)
        c2, c1, c0 = np.polyfit(vx[use], force[use], 2)
        resistance = plant.params.resistance
        return (
            "coast_down",
            run,
            {
                "drag_coefficient_fit": float(
                    2 * c2 / (resistance.air_density_kg_per_m3 * resistance.frontal_area_m2)
                ),
                "rolling_resistance_fit": float(c0 / (mass * G)),
                "coast_down_effective_mass_kg": float(mass + spin_inertia / radius**2),
                "coast_down_fit_n": {
                    "constant": float(c0),
                    "linear": float(c1),
                    "quadratic": float(c2),
                },
                "drag_coefficient_true": resistance.drag_coefficient,
                "rolling_resistance_true": resistance.rolling_resistance,
            },
        )


def _linear_range_top(plant: Sedan) -> float:
    """The linear range: up to 4 m/s^2, or less than half the friction limit on a slippery road."""
    return min(4.0, 0.45 * plant.params.tire.road_friction * G)


def _wheelbase(plant: Sedan) -> float:
    return float(plant.model.body("corner_fl").pos[0] - plant.model.body("corner_rl").pos[0])


def plot(runs: dict[str, Trajectory], metrics: dict, plant: Sedan, path: Path) -> None:
    """One page, six panels: the evidence behind each characterization number."""
    fig = Figure(figsize=(15, 8.5))
    axes = fig.subplots(2, 3)
    name = plant.params.name

    _circle_panel(axes[0, 0], runs, metrics, plant)
    _step_steer_panel(axes[0, 1], runs, metrics, plant)
    _braking_panel(axes[0, 2], runs, metrics, plant)
    _launch_panel(axes[1, 0], runs, metrics, plant)
    _low_speed_panel(axes[1, 1], runs, metrics, plant)
    _coast_down_panel(axes[1, 2], runs, metrics, plant)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    fig.suptitle(f"Plant characterization: {name}")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def _circle_panel(ax: Axes, runs: dict[str, Trajectory], metrics: dict, plant: Sedan) -> None:
    """ISO 4138 ramp: steering against lateral acceleration, and the held angles."""
    ramp = runs["steady_state_circle"]
    lateral = moving_average(ramp.lateral_accel_mps2, int(0.5 / plant.dt))
    ax.plot(lateral / G, ramp.inputs[:, 0], lw=1.2)
    ax.set(
        xlabel="lateral acceleration (g)",
        ylabel="steering-wheel angle (deg)",
        title=f"ISO 4138 ramp at {ramp.states[0, 0] * 3.6:.0f} km/h\n"
        f"K = {metrics['understeer_gradient_deg_per_g']:.2f} deg/g, "
        f"max a_y = {metrics['max_lateral_accel_mps2']:.2f} m/s²",
    )
    circle_speed = ramp.states[0, 0]
    held = [
        p
        for p in metrics["steady_state"]["points"]
        if abs(p["speed_mps"] - circle_speed) < 0.05 * circle_speed
    ]
    ax.plot(
        [p["lateral_accel_mps2"] / G for p in held],
        [p["steer_wheel_deg"] for p in held],
        "o",
        label=f"held angles: K = {metrics['understeer_gradient_steady_state_deg_per_g']:.2f} deg/g",
    )
    ax.axvline(plant.params.tire.road_friction, color="k", ls=":", label="μ g")
    ax.legend(loc="upper left")


def _step_steer_panel(ax: Axes, runs: dict[str, Trajectory], metrics: dict, plant: Sedan) -> None:
    """ISO 7401 step steer: yaw rate against the road-wheel angle."""
    step = runs["step_steer"]
    ax.plot(step.time_s, np.rad2deg(step.states[:, 2]), label="yaw rate (deg/s)")
    ax.plot(
        step.time_s,
        step.inputs[:, 0] / plant.params.steering.steering_ratio * 10,
        ls="--",
        label="road-wheel angle ×10 (deg)",
    )
    rise = metrics["yaw_rate_rise_time_s"]
    ax.set(
        xlabel="time (s)",
        title=f"ISO 7401 step steer at 80 km/h\n"
        f"response {rise if rise is None else f'{rise:.3f}'} s, "
        f"overshoot {metrics['yaw_rate_overshoot']:.3f}",
    )
    ax.legend()


def _braking_panel(ax: Axes, runs: dict[str, Trajectory], metrics: dict, plant: Sedan) -> None:
    """Full braking from 100 km/h: speed against distance."""
    brake = runs["braking"]
    ax.plot(brake.distance_m, brake.states[:, 0] * 3.6)
    ax.set(
        xlabel="distance (m)",
        ylabel="speed (km/h)",
        title=f"full braking from 100 km/h: {metrics['braking_distance_100kph_m']:.1f} m",
    )


def _launch_panel(ax: Axes, runs: dict[str, Trajectory], metrics: dict, plant: Sedan) -> None:
    """Launch at full throttle: speed against time."""
    launch = runs["launch"]
    ax.plot(launch.time_s, launch.states[:, 0] * 3.6)
    ax.axhline(100, color="k", ls=":")
    accel = metrics["accel_0_100kph_s"]
    ax.set(
        xlabel="time (s)",
        ylabel="speed (km/h)",
        title=f"launch at throttle {Sedan.input_high[1]}: 0-100 km/h "
        f"{'not reached' if accel is None else f'{accel:.1f} s'}",
    )


def _low_speed_panel(ax: Axes, runs: dict[str, Trajectory], metrics: dict, plant: Sedan) -> None:
    """Low-speed turn: yaw rate against the kinematic v δ / L."""
    low = runs["low_speed_turn"]
    delta = np.deg2rad(low.inputs[:, 0]) / plant.params.steering.steering_ratio
    ax.plot(low.time_s, low.states[:, 2], label="yaw rate")
    ax.plot(low.time_s, low.states[:, 0] * delta / _wheelbase(plant), ls="--", label="v δ / L")
    ax.set(
        xlabel="time (s)",
        ylabel="rad/s",
        title=f"low-speed turn: kinematic error {metrics['kinematic_yaw_rate_error']:.2%}",
    )
    ax.legend()


def _coast_down_panel(ax: Axes, runs: dict[str, Trajectory], metrics: dict, plant: Sedan) -> None:
    """Coast-down: the measured resistance against its fit."""
    coast = runs["coast_down"]
    speed = coast.states[:, 0]
    mass = metrics["coast_down_effective_mass_kg"]
    ax.plot(
        speed * 3.6,
        -np.gradient(speed, coast.time_s) * mass,
        lw=3,
        alpha=0.5,
        label="measured (effective mass × deceleration)",
    )
    fit = metrics["coast_down_fit_n"]
    ax.plot(
        speed * 3.6,
        fit["constant"] + fit["linear"] * speed + fit["quadratic"] * speed**2,
        ls="--",
        color="k",
        label="fit A + B v + C v²",
    )
    ax.set(
        xlabel="speed (km/h)",
        ylabel="resistance (N)",
        title=f"coast-down: Cd {metrics['drag_coefficient_fit']:.3f} "
        f"(true {metrics['drag_coefficient_true']:.3f})\n"
        f"Cr {metrics['rolling_resistance_fit']:.4f} "
        f"(true {metrics['rolling_resistance_true']:.4f})",
    )
    ax.legend()
