"""Sweeps run through Hydra's launchers: jobs side by side on this machine's cores (joblib),
on Slurm (submitit) and on Ray; jobs that share a dataset collect it once."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import compose
from tests.test_pipeline import TINY

# Every job log line names the process that wrote it.
PID_LOG = "hydra.job_logging.formatters.simple.format='pid=%(process)d %(message)s'"


def sweep(tmp: Path, *overrides: str) -> tuple[int, Path]:
    """Run ``python -m harness -m`` with tiny jobs; return the sweep's own pid and its directory."""
    # A process: the launcher starts the jobs, in processes of its own the tests tell apart.
    sweep_dir = tmp / "multirun"
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "harness",
            "-m",
            *TINY,
            "learner=edmd",
            f"data.root={tmp}/datasets",
            f"hydra.sweep.dir={sweep_dir}",
            PID_LOG,
            *overrides,
        ],
        cwd=tmp,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    output, _ = process.communicate(timeout=600)
    assert process.returncode == 0, output[-3000:]
    return process.pid, sweep_dir


def jobs(sweep_dir: Path) -> list[Path]:
    return sorted(p.parent for p in sweep_dir.glob("*/.hydra"))


def job_pids(job: Path) -> set[int]:
    (log,) = job.glob("*.log")
    return {int(line.split()[0][4:]) for line in log.read_text().splitlines() if line[:4] == "pid="}


def data_metrics(job: Path) -> dict:
    assert not (job / "error.json").exists(), (job / "error.json").read_text()
    return json.loads((job / "metrics.json").read_text())["data"]


def assert_two_jobs_collected_one_dataset_once(sweep_dir: Path) -> None:
    data = [data_metrics(job) for job in jobs(sweep_dir)]
    assert len(data) == 2
    assert data[0]["key"] == data[1]["key"]
    assert sorted(d["episodes_collected"] for d in data) == [0, 3]  # one drove all, one reused
    dataset = Path(data[0]["path"])
    assert len(list(dataset.glob("episode_*.npz"))) == 3
    assert not list(dataset.glob(".*.tmp"))  # no half-written file left behind


@pytest.fixture(scope="module")
def joblib_sweep(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, Path]:
    """Two jobs (seeds 0, 1) with one data config, two at a time on this machine."""
    tmp = tmp_path_factory.mktemp("joblib")
    return sweep(tmp, "hydra/launcher=local_cores", "hydra.launcher.n_jobs=2", "seed=0,1")


def test_local_cores_runs_the_jobs_at_once_in_two_worker_processes(joblib_sweep) -> None:
    sweep_pid, sweep_dir = joblib_sweep
    pids = [job_pids(job) for job in jobs(sweep_dir)]
    assert len(pids) == 2 and all(len(p) == 1 for p in pids), pids
    (first,), (second,) = pids
    assert len({first, second, sweep_pid}) == 3  # two workers, neither the sweep's own process
    # Each job's config is written as it starts and its metrics as it ends: the spans overlap.
    spans = [
        ((job / ".hydra" / "config.yaml").stat().st_mtime, (job / "metrics.json").stat().st_mtime)
        for job in jobs(sweep_dir)
    ]
    (start_a, end_a), (start_b, end_b) = spans
    assert start_a < end_b and start_b < end_a


def test_concurrent_jobs_that_share_a_data_config_collect_it_once(joblib_sweep) -> None:
    _, sweep_dir = joblib_sweep
    assert_two_jobs_collected_one_dataset_once(sweep_dir)


def launcher_config(*overrides: str):
    return compose(*overrides, as_app=True).hydra


def test_the_slurm_config_extends_the_submitit_plugin_with_this_projects_defaults() -> None:
    hydra = launcher_config("hydra/launcher=slurm", "hydra.launcher.partition=cpu")
    launcher = hydra.launcher
    assert launcher._target_ == (
        "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    )
    assert (launcher.timeout_min, launcher.cpus_per_task, launcher.mem_gb) == (240, 2, 8)
    assert launcher.array_parallelism == 32
    assert launcher.partition == "cpu"
    assert launcher.submitit_folder == f"{hydra.sweep.dir}/.submitit/%j"  # beside the jobs
    assert hydra.runtime.choices["hydra/launcher"] == "slurm"


def test_local_cores_uses_every_core_unless_told() -> None:
    launcher = launcher_config("hydra/launcher=local_cores").launcher
    assert launcher._target_.endswith("JoblibLauncher") and launcher.n_jobs == -1


def test_a_job_submitted_through_submitit_runs_in_its_own_process(tmp_path: Path) -> None:
    """submitit's local executor pickles and runs the job as Slurm would, without Slurm."""
    sweep_pid, sweep_dir = sweep(tmp_path, "hydra/launcher=submitit_local")
    (job,) = jobs(sweep_dir)
    assert data_metrics(job)["episodes_collected"] == 3
    (pid,) = job_pids(job)
    assert pid != sweep_pid
    assert list((sweep_dir / ".submitit").glob("*/*_submitted.pkl"))


# Ray: `make test-ray` installs the `ray` extra (about 60 packages) and runs these.


@pytest.fixture
def ray_cluster():
    """A Ray head node on 127.0.0.1 that this test starts (2 CPUs) and stops; its address."""
    ray = pytest.importorskip("ray")
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    context = ray.init(
        address="local",
        num_cpus=2,
        include_dashboard=False,
        _node_ip_address="127.0.0.1",
        object_store_memory=78_643_200,
    )
    yield context.address_info["gcs_address"]
    ray.shutdown()


@pytest.mark.slow
def test_ray_runs_a_two_job_sweep_on_a_running_cluster(ray_cluster: str, tmp_path: Path) -> None:
    sweep_pid, sweep_dir = sweep(
        tmp_path,
        "hydra/launcher=ray_cluster",
        f"hydra.launcher.ray.init.address={ray_cluster}",
        "hydra.launcher.ray.remote.num_cpus=1",  # the test cluster has 2 CPUs: both jobs at once
        "seed=0,1",
    )
    assert_two_jobs_collected_one_dataset_once(sweep_dir)
    pids = set().union(*(job_pids(job) for job in jobs(sweep_dir)))
    assert len(pids) == 2 and sweep_pid not in pids  # in two Ray workers


@pytest.mark.slow
def test_ray_local_starts_its_own_instance_for_the_sweep(tmp_path: Path) -> None:
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    _, sweep_dir = sweep(tmp_path, "hydra/launcher=ray_local", "seed=0,1")
    assert_two_jobs_collected_one_dataset_once(sweep_dir)
