"""The time-varying MPC's QP, condensed (ours) against sparse multiple shooting, on the same QPs.

``python -m bench.qp_formulation [--quick] [--models DIR] [--learners bilinear_edmd,input_edmd]``.
Which formulation should a linearised lifted model (N ≈ 100) be solved in? This is the
controlled experiment: one factor, the formulation, on exactly the same problems.

DE-MPC closes the loop on the sedan through the 80 km/h ISO 3888-1 lane change at 60/50
(tracking states, ``linearization: predicted``: a model A_k, B_k, d_k per horizon step, the
hardest case) and every step's linearisation, measured state, last input and reference are
recorded. Each recorded QP is then built and solved again, in order, by

- **condensed** (ours, ``TimeVaryingQP``): Θ in output space (C S_j, three rows a step), the
  Hessian and its Cholesky factor, DAQP's rows (the preparation), then the free response and
  DAQP warm-started from the last step's working set (the feedback); also with the model of
  ``linearization: frozen`` (the default since 2026-11-27: A_0, B_0 held over the horizon), for
  its time;
- **sparse, multistage**: the same QP in multiple-shooting form (per stage Δv_k, v_k, z_{k+1},
  the dynamics as equality constraints; the slack ε last) for PIQP's sparse interface with its
  block-tridiagonal KKT solver (``sparse_multistage``, the structure HPIPM's Riccati recursion
  exploits), set up afresh each step (the pattern of A_k changes with the model);
- **sparse, LDLᵀ**: the same with PIQP's general sparse KKT factorization (``sparse_ldlt``).

Both forms have one optimum (R > 0): the table gives how far each answer's increments are from
the condensed one's (normalized input units, 1 = an input's range), so the times compare the
same answer. Times are per step, ms, median / p99.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import piqp
import scipy.sparse as sp

from bench.controller_solve_time import fit_models
from bench.machine import describe
from controllers.blas import single_threaded


@dataclass(frozen=True)
class Problem:
    """One step's QP data: the model along the horizon and what the feedback measured."""

    A: np.ndarray  # (Np, N, N)
    B: np.ndarray  # (Np, N, m)
    d: np.ndarray  # (Np, N)
    z: np.ndarray  # (N,)
    v_prev: np.ndarray  # (m,)
    y_ref: np.ndarray  # (n Np,)
    dv: np.ndarray  # (Nc, m): the closed loop's answer


def record(model_path: str, horizon: tuple[int, int]) -> tuple[Any, list[Problem]]:
    """The lane change under DE-MPC (states, predicted) and every step's QP (controller, QPs)."""
    from controllers import DEMPCConfig
    from controllers.time_varying_qp import TimeVaryingQP
    from harness.evaluation.tracking import track
    from harness.plant import Sedan
    from harness.recorder import Recorder
    from harness.references import DoubleLaneChange
    from learners import load

    model: Any = load(model_path)
    plant, lane_change = Sedan(), DoubleLaneChange()
    config = DEMPCConfig(Np=horizon[0], Nc=horizon[1], linearization="predicted")
    controller = config(model, plant.dt)
    qp = controller.qp
    assert isinstance(qp, TimeVaryingQP), "the experiment needs a linearised model"
    problems: list[Problem] = []
    latest: dict[str, np.ndarray] = {}
    model_theta, solve = qp.model_theta, qp.solve

    def recording_theta(A: np.ndarray, B: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        K = A.shape[0]
        latest.update(A=A.copy(), B=B.copy(), d=np.zeros((K, A.shape[1])) if d is None else d)
        return model_theta(A, B, d)

    def recording_solve(z: np.ndarray, v_prev: np.ndarray, y_ref: np.ndarray) -> Any:
        solution = solve(z, v_prev, y_ref)
        if solution.ok:
            problems.append(
                Problem(
                    **latest,
                    z=z.copy(),
                    v_prev=v_prev.copy(),
                    y_ref=y_ref.copy(),
                    dv=solution.dv.copy(),
                )
            )
        return solution

    qp.model_theta = recording_theta  # type: ignore[method-assign]
    qp.solve = recording_solve  # type: ignore[method-assign]
    reference = lane_change.build(plant.dt, [])
    track(plant, controller, reference, name="record", recorder=Recorder())
    qp.model_theta, qp.solve = model_theta, solve  # type: ignore[method-assign]
    return controller, problems


def condensed(
    controller: Any, problems: list[Problem], frozen: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(prepare, feedback) seconds per step and the increments, with our TimeVaryingQP;
    ``frozen``: the first step's A, B, d held over the horizon (the default linearisation's
    QP: another model, so another answer)."""
    qp = controller.qp
    qp.reset()
    times, answers = [], []
    for p in problems:
        start = time.perf_counter()
        if frozen:
            qp.set_model(p.A[:1], p.B[:1], p.d[:1])
        else:
            qp.set_model(p.A, p.B, p.d)
        qp.prepare_solvers()
        prepared = time.perf_counter()
        solution = qp.solve(p.z, p.v_prev, p.y_ref)
        done = time.perf_counter()
        times.append((prepared - start, done - prepared))
        answers.append(solution.dv)
    return np.array(times), np.array(answers)


class MultipleShooting:
    """The same QP with the states as variables: per stage k = 0..Np-1 the variables
    [Δv_k (k < Nc), v_k, z_{k+1}], then ε; the dynamics and the input integration as
    equality rows (block-banded), the rate limits as rows, the input bounds as boxes."""

    def __init__(self, qp: Any) -> None:
        self.qp = qp
        self.N, self.m, self.n = qp.N, qp.m, qp.n
        self.Np, self.Nc = qp.Np, qp.Nc
        self.offsets: list[tuple[int | None, int, int]] = []  # (Δv, v, z) column of each stage
        column = 0
        for k in range(self.Np):
            dv = column if k < self.Nc else None
            column += self.m if k < self.Nc else 0
            self.offsets.append((dv, column, column + self.m))
            column += self.m + self.N
        self.eps = column
        self.size = column + 1

    def matrices(self, p: Problem) -> dict[str, Any]:
        """P, c, A, b, G, h_l, h_u, x_l, x_u of PIQP's sparse problem for step p."""
        qp, N, m = self.qp, self.N, self.m
        cqc = 2 * qp.C.T @ qp.Q @ qp.C
        cq = 2 * qp.C.T @ qp.Q
        P = sp.lil_matrix((self.size, self.size))
        c = np.zeros(self.size)
        rows: list[int] = []
        cols: list[int] = []
        vals: list[float] = []
        b: list[float] = []
        g_rows, g_cols, g_vals = [], [], []
        equality = inequality = 0
        rate = 1.0 / qp.dv_max

        def block(r0: int, c0: int, matrix: np.ndarray) -> None:
            r, q = np.indices(matrix.shape)
            rows.extend((r0 + r).ravel())
            cols.extend((c0 + q).ravel())
            vals.extend(matrix.ravel())

        for k, (dv, v, z) in enumerate(self.offsets):
            P[z : z + N, z : z + N] = cqc
            c[z : z + N] = -cq @ p.y_ref[k * self.n : (k + 1) * self.n]
            # v_k - v_{k-1} - Δv_k = v_prev (k = 0) or 0
            block(equality, v, np.eye(m))
            if k:
                block(equality, self.offsets[k - 1][1], -np.eye(m))
            if dv is not None:
                block(equality, dv, -np.eye(m))
                P[dv : dv + m, dv : dv + m] = 2 * qp._R
                for j in range(m):
                    for sign in (1.0, -1.0):  # ±Δv/Δv_max - ε <= 1
                        g_rows += [inequality, inequality]
                        g_cols += [dv + j, self.eps]
                        g_vals += [sign * rate[j], -1.0]
                        inequality += 1
            b.extend(p.v_prev if k == 0 else np.zeros(m))
            equality += m
            # z_{k+1} - A_k z_k - B_k v_k = d_k (+ A_0 z_0 at k = 0)
            block(equality, z, np.eye(N))
            block(equality, v, -p.B[k])
            if k:
                block(equality, self.offsets[k - 1][2], -p.A[k])
            b.extend(p.d[k] + (p.A[0] @ p.z if k == 0 else 0.0))
            equality += N
        P[self.eps, self.eps] = 2 * qp.rho
        A = sp.csc_matrix((vals, (rows, cols)), shape=(equality, self.size))
        G = sp.csc_matrix((g_vals, (g_rows, g_cols)), shape=(inequality, self.size))
        x_l = np.full(self.size, -np.inf)
        x_u = np.full(self.size, np.inf)
        for _, v, _ in self.offsets:
            x_l[v : v + m], x_u[v : v + m] = qp.v_min, qp.v_max
        x_l[self.eps] = 0.0
        return {
            "P": sp.triu(P.tocsc(), format="csc"),
            "c": c,
            "A": A,
            "b": np.asarray(b, dtype=float),
            "G": G,
            "h_l": np.full(G.shape[0], -np.inf),
            "h_u": np.ones(G.shape[0]),
            "x_l": x_l,
            "x_u": x_u,
        }

    def increments(self, x: np.ndarray) -> np.ndarray:
        return np.array([x[dv : dv + self.m] for dv, _, _ in self.offsets[: self.Nc]])


def sparse(
    controller: Any, problems: list[Problem], kkt_solver: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(build, solve) seconds per step, the increments and PIQP's iterations."""
    form = MultipleShooting(controller.qp)
    times, answers, iterations = [], [], []
    for p in problems:
        start = time.perf_counter()
        data = form.matrices(p)
        built = time.perf_counter()
        solver = piqp.SparseSolver()
        solver.settings.eps_abs = controller.qp.tol
        solver.settings.eps_duality_gap_abs = controller.qp.tol
        solver.settings.kkt_solver = getattr(piqp.KKTSolver, kkt_solver)
        solver.setup(**data)
        status = solver.solve()
        done = time.perf_counter()
        if status != piqp.PIQP_SOLVED:
            raise RuntimeError(f"PIQP ({kkt_solver}) did not solve a recorded QP: {status}")
        times.append((built - start, done - built))
        answers.append(form.increments(np.asarray(solver.result.x)))
        iterations.append(solver.result.info.iter)
    return np.array(times), np.array(answers), np.array(iterations)


def _ms(seconds: np.ndarray) -> str:
    return f"{1e3 * np.median(seconds):.3f} / {1e3 * np.percentile(seconds, 99):.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 drives of 15 s to fit on")
    parser.add_argument("--models", default="", help="folder to keep fitted models in, reused")
    parser.add_argument("--learners", default="bilinear_edmd,input_edmd")
    parser.add_argument("--horizon", default="60/50")
    parser.add_argument("--every", type=int, default=4, help="solve every k-th recorded QP")
    args = parser.parse_args()
    Np, Nc = (int(value) for value in args.horizon.split("/"))
    names = args.learners.split(",")
    print(f"machine: {describe()}; load average {os.getloadavg()[0]:.2f} at start")
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(args.models or scratch)
        folder.mkdir(parents=True, exist_ok=True)
        paths = fit_models(folder, args.quick, names)
        print(
            "\n| model | N | formulation | prepare / build ms | solve ms | whole ms (median / p99) "
            "| PIQP iterations (median) | max \\|ΔV − condensed\\| |"
        )
        print("|" + "---|" * 8)
        for name in names:
            with single_threaded():  # as DE-MPC runs (controllers/blas.py)
                compare(name, paths[name], (Np, Nc), args.every)
    print(f"\nload average {os.getloadavg()[0]:.2f} at the end.")


def compare(name: str, path: str, horizon: tuple[int, int], every: int) -> None:
    """One model's rows of the table."""
    controller, recorded = record(path, horizon)
    problems = recorded[::every]
    N = controller.qp.N
    times, reference = condensed(controller, problems)
    closed_loop = np.abs(reference - np.array([p.dv for p in problems])).max()
    print(
        f"| {name} | {N} | condensed + DAQP (ours) | {_ms(times[:, 0])} | "
        f"{_ms(times[:, 1])} | {_ms(times.sum(axis=1))} | – | "
        f"{closed_loop:.1e} (against the closed loop's) |",
        flush=True,
    )
    times, _ = condensed(controller, problems, frozen=True)
    print(
        f"| {name} | {N} | condensed + DAQP, frozen (A_0, B_0 held: the default) | "
        f"{_ms(times[:, 0])} | {_ms(times[:, 1])} | {_ms(times.sum(axis=1))} | – | "
        "– (another model) |",
        flush=True,
    )
    for kkt in ("sparse_multistage", "sparse_ldlt"):
        times, answers, iterations = sparse(controller, problems, kkt)
        print(
            f"| {name} | {N} | multiple shooting + PIQP {kkt} | {_ms(times[:, 0])} | "
            f"{_ms(times[:, 1])} | {_ms(times.sum(axis=1))} | "
            f"{np.median(iterations):.0f} | {np.abs(answers - reference).max():.1e} |",
            flush=True,
        )
    print(f"({name}: {len(problems)} of {len(recorded)} recorded QPs)", flush=True)


if __name__ == "__main__":
    main()
