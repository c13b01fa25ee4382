"""The spectrum of a Koopman model: its eigenvalues, and the modes outside the unit circle named.

A lifted-linear model z⁺ = A z + B v grows without bound along every eigenvector of A with
|λ| > 1, whatever the input: such a mode makes long open-loop predictions diverge and an MPC's
predictions unreliable. A bilinear model z⁺ = A z + B v + Σⱼ v̄ⱼ Hⱼ z holding the input v has
the state matrix A + Σⱼ v̄ⱼ Hⱼ; :func:`spectrum` examines it at zero input (v̄ = 0, i.e. A) and
at every corner of the normalized input box [0, 1]^m, the extremes the data spans.

At the plant's 100 Hz every mode lies near 1 (a step barely moves the state) and a constant
observable has λ = 1 exactly, so a mode counts as unstable when |λ| > 1 + ``tolerance`` (1e-6);
its ``doubling_time_s`` = ln 2 · dt / ln|λ| says whether it matters over a drive (a mode that
doubles in 10 minutes is harmless in a 30 s prediction; one that doubles in 1 s is not). Each
unstable mode is named by the lifted coordinate that dominates its eigenvector: a state's name
where ``C_`` reads that coordinate as the state (``C_ = [I 0]``), else ``z<i>``.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from harness.core.contracts import INPUT_NAMES, STATE_NAMES, BilinearModel, LiftedModel
from harness.output import save_figure
from harness.recorder import Recorder

__all__ = [
    "TOLERANCE",
    "plot_spectrum",
    "record_spectrum",
    "spectrum",
    "spectrum_figure",
    "state_matrices",
]

TOLERANCE = 1e-6


def state_matrices(model: LiftedModel) -> dict[str, np.ndarray]:
    """The state matrices whose eigenvalues matter, by a label: ``A`` for a lifted-linear model;
    for a bilinear one ``zero input`` (A) and ``steer_wheel_deg=max,pedal=min`` etc. (the
    corners of the normalized input box, where min is v = 0 and max is v = 1)."""
    if model.dynamics != "bilinear":
        return {"A": np.asarray(model.A_)}
    assert isinstance(model, BilinearModel)
    matrices = {"zero input": np.asarray(model.A_)}
    m = model.H_.shape[0]
    names = INPUT_NAMES if m == len(INPUT_NAMES) else tuple(f"v{j}" for j in range(m))
    for corner in itertools.product((0.0, 1.0), repeat=m):
        vbar = np.array(corner) - model.v0_
        label = ",".join(
            f"{name}={'max' if c else 'min'}" for name, c in zip(names, corner, strict=True)
        )
        matrices[label] = model.A_ + np.einsum("j,jnk->nk", vbar, model.H_)
    return matrices


def _coordinate_names(model: LiftedModel) -> list[str]:
    """A name per lifted coordinate: the state ``C_`` reads off it alone, else ``z<i>``."""
    c = np.asarray(model.C_)
    names = [f"z{i}" for i in range(c.shape[1])]
    for row, state in zip(c, STATE_NAMES, strict=False):
        nonzero = np.flatnonzero(row)
        if len(nonzero) == 1 and row[nonzero[0]] == 1.0:
            names[nonzero[0]] = state
    return names


def spectrum(
    model: LiftedModel, dt: float, *, tolerance: float = TOLERANCE
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``metrics.json``'s ``spectrum`` section and the eigenvalues of every state matrix.

    Metrics: ``max_abs_eigenvalue`` (over every matrix), ``unstable_modes`` (a list, each with
    its ``matrix``, ``eigenvalue`` [re, im], ``abs``, ``doubling_time_s`` and ``dominant``
    lifted coordinate; a complex pair is one mode), and per matrix its ``max_abs_eigenvalue``
    and ``unstable`` count.
    """
    names = _coordinate_names(model)
    eigenvalues: dict[str, np.ndarray] = {}
    per_matrix: dict[str, dict[str, Any]] = {}
    unstable: list[dict[str, Any]] = []
    for label, matrix in state_matrices(model).items():
        values, vectors = np.linalg.eig(matrix)
        eigenvalues[label] = values
        # a complex pair is one mode: count and name it once, by its upper half
        outside = np.flatnonzero((np.abs(values) > 1.0 + tolerance) & (values.imag >= 0))
        per_matrix[label] = {
            "max_abs_eigenvalue": float(np.abs(values).max()),
            "unstable": len(outside),
        }
        for i in outside[np.argsort(-np.abs(values[outside]))]:
            magnitude = float(abs(values[i]))
            unstable.append(
                {
                    "matrix": label,
                    "eigenvalue": [float(values[i].real), float(values[i].imag)],
                    "abs": magnitude,
                    "doubling_time_s": math.log(2.0) * dt / math.log(magnitude),
                    "dominant": names[int(np.argmax(np.abs(vectors[:, i])))],
                }
            )
    metrics = {
        "max_abs_eigenvalue": max(m["max_abs_eigenvalue"] for m in per_matrix.values()),
        "unstable_modes": unstable,
        "tolerance": tolerance,
        "matrices": per_matrix,
    }
    return metrics, eigenvalues


def record_spectrum(
    recorder: Recorder, eigenvalues: dict[str, np.ndarray], prefix: str = ""
) -> None:
    """``<prefix>spectrum/<matrix>/{abs, real, imag}`` per mode (the ``mode`` timeline)."""
    for label, values in eigenvalues.items():
        order = np.argsort(-np.abs(values))
        recorder.series(
            f"{prefix}spectrum/{label}",
            np.arange(len(values), dtype=np.int64),
            {"abs": np.abs(values[order]), "real": values[order].real, "imag": values[order].imag},
            timeline="mode",
        )


def plot_spectrum(eigenvalues: dict[str, np.ndarray], path: Path, title: str = "") -> Path:
    """``spectrum.png``: :func:`spectrum_figure`, saved at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(spectrum_figure(eigenvalues, title), path)


def spectrum_figure(eigenvalues: dict[str, np.ndarray], title: str = "") -> Figure:
    """The unit circle and every matrix's eigenvalues; beside it, a zoom around λ = 1."""
    fig = Figure(figsize=(10, 4.8))
    whole, zoom = fig.subplots(1, 2)
    angle = np.linspace(0.0, 2.0 * np.pi, 721)
    markers = "ox+^sv<>dp"
    for ax in (whole, zoom):
        ax.plot(np.cos(angle), np.sin(angle), "k-", lw=0.8)
        for k, (label, values) in enumerate(eigenvalues.items()):
            ax.plot(
                values.real,
                values.imag,
                markers[k % len(markers)],
                color=f"C{k}",
                ms=5,
                mfc="none",
                label=f"{label} (max |λ| {np.abs(values).max():.6f})",
            )
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("Re λ")
    whole.set_ylabel("Im λ")
    whole.set_title(title or "eigenvalues and the unit circle", fontsize=9)
    near = np.concatenate([v[np.abs(v - 1.0) < 0.1] for v in eigenvalues.values()])
    reach = max(float(np.abs(near - 1.0).max()) * 1.2, 1e-3) if near.size else 0.05
    zoom.set_xlim(1.0 - reach, 1.0 + reach)
    zoom.set_ylim(-reach, reach)
    zoom.set_title("around λ = 1 (100 Hz: slow modes lie here)", fontsize=9)
    whole.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    return fig
