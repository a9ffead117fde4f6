"""The launcher configs of ``conf/hydra/launcher``: real multiruns with joblib, on a real Slurm cluster, on Ray.

The Slurm test starts a single-node cluster of its own (``tests/slurm/cluster.py``)
from Debian's ``slurmctld``, ``slurmd`` and ``munge`` packages, which ``.ci/run``
installs. Without those packages it is skipped, except in CI (the environment
variable ``CI`` set), where it fails saying what is missing.
"""

import csv
import os
import subprocess
import sys
import time

import pytest

from slurm.cluster import SlurmCluster, SlurmStartError, unavailable_reason

SWEEP = ["-m", "seed=1,2", "tasks=example", "world.physics=static", "progress=false"]


def _sweep(sweep_dir, *extra, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "overhang_framework", *SWEEP, f"hydra.sweep.dir={sweep_dir}",
                           *extra], capture_output=True, text=True, env=env, timeout=timeout)


def _results(sweep_dir):
    with open(sweep_dir / "results.csv") as fh:
        return list(csv.DictReader(fh))


def _assert_complete(proc, sweep_dir):
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    rows = _results(sweep_dir)
    assert [(r["job"], r["status"], r["seed"], r["tasks"], r["world.physics"]) for r in rows] == [
        ("0", "complete", "1", "example", "static"), ("1", "complete", "2", "example", "static")]
    assert all(r["episodes"] == r["episodes_expected"] == "1" and float(r["reward_mean"]) > 0 for r in rows)
    assert f"{sweep_dir / 'results.csv'}: 2 jobs, 2 complete" in proc.stdout
    return rows


def _launcher(name, *overrides):
    from overhang_framework.config import compose_config

    return compose_config([f"hydra/launcher={name}", "jobs=3", *overrides], return_hydra_config=True).hydra.launcher


# ---- the configs ------------------------------------------------------------------------------

def test_local_is_joblib_with_one_process_per_core():
    launcher = _launcher("local")
    assert launcher._target_.endswith("joblib_launcher.JoblibLauncher")
    assert launcher.n_jobs == -1 and launcher.prefer == "processes"


def test_slurm_extends_submitit_slurm_and_asks_the_cpus_of_the_run():
    launcher = _launcher("slurm")
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert (launcher.cpus_per_task, launcher.mem_gb, launcher.timeout_min, launcher.partition) == (3, 2, 60, None)
    assert launcher.tasks_per_node == launcher.nodes == 1
    assert launcher.array_parallelism == 64
    # the plugin's schema still applies
    from omegaconf.errors import ValidationError

    with pytest.raises(Exception) as info:
        _launcher("slurm", "hydra.launcher.timeout_min=soon")
    assert isinstance(info.value.__cause__, ValidationError) or "timeout_min" in str(info.value)


def test_submitit_is_submitit_local():
    launcher = _launcher("submitit")
    assert launcher._target_.endswith("submitit_launcher.LocalLauncher")
    assert launcher.cpus_per_task == 3


def test_the_plugins_own_launcher_configs_are_not_shadowed():
    assert _launcher("joblib").n_jobs == -1
    assert _launcher("submitit_slurm").cpus_per_task is None


def _ray_installed():
    try:
        import hydra_plugins.hydra_ray_launcher  # noqa: F401
        return True
    except ImportError:
        return False


@pytest.mark.skipif(_ray_installed(), reason="the Ray launcher is installed")
@pytest.mark.parametrize("name", ["ray_sweep", "ray"])
def test_ray_without_its_extra_stops_with_one_line_naming_the_extra(tmp_path, capsys, name):
    from overhang_framework.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main([*SWEEP, f"hydra/launcher={name}", f"hydra.sweep.dir={tmp_path / 'sweep'}"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: hydra/launcher={name} needs hydra-ray-launcher, which is not installed; it is the "
                   "optional extra 'ray': pip install -e '.[ray]'"]
    assert not (tmp_path / "sweep").exists()


def test_joining_a_ray_cluster_without_clearing_the_object_store_size_is_refused_in_one_line():
    from omegaconf import OmegaConf

    from overhang_framework.errors import OverhangError
    from overhang_framework.preflight import _check_launcher

    def cfg(**init):
        return OmegaConf.create({"hydra": {"launcher": {
            "_target_": "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher",
            "ray": {"init": init, "remote": {}}}}})

    with pytest.raises(OverhangError, match=r"also needs \+hydra.launcher.ray.init.object_store_memory=null"):
        _check_launcher(cfg(address="auto"))
    _check_launcher(cfg(address="auto", object_store_memory=None))
    _check_launcher(cfg(address=None))


# ---- real multiruns ---------------------------------------------------------------------------

def test_a_joblib_sweep_writes_results_csv(tmp_path):
    proc = _sweep(tmp_path, "hydra/launcher=local", "hydra.launcher.n_jobs=2")
    _assert_complete(proc, tmp_path)
    assert "Joblib.Parallel(n_jobs=2," in proc.stdout  # the jobs went through joblib, two at a time


@pytest.fixture(scope="module")
def slurm_cluster():
    reason = unavailable_reason()
    if reason:
        if os.environ.get("CI") or "not found" not in reason:
            pytest.fail(f"cannot start the test Slurm cluster: {reason}", pytrace=False)
        pytest.skip(reason)
    cluster = SlurmCluster(timeout=60)
    try:
        cluster.start()
    except SlurmStartError as err:
        pytest.fail(f"the test Slurm cluster did not start: {err}", pytrace=False)
    try:
        yield cluster
    finally:
        cluster.stop()


def test_a_slurm_sweep_writes_results_csv(slurm_cluster, tmp_path):
    # the jobs run as root under slurmd on this machine: a tmp_path is a filesystem they share
    started = time.monotonic()
    proc = _sweep(tmp_path, "hydra/launcher=slurm", "hydra.launcher.mem_gb=1", "hydra.launcher.timeout_min=5",
                  env=slurm_cluster.env, timeout=240)
    _assert_complete(proc, tmp_path)
    # the jobs were one Slurm array with the config's resources (submitit caps % at the array size)
    (script,) = (tmp_path / ".submitit").glob("*/*_submission.sh")
    text = script.read_text()
    array_id = script.parent.name
    for option in ("--array=0-1%2", "--cpus-per-task=1", "--mem=1GB", "--time=5", "--ntasks-per-node=1"):
        assert f"#SBATCH {option}\n" in text, text
    for job in ("0", "1"):
        assert (tmp_path / ".submitit" / f"{array_id}_{job}" / f"{array_id}_{job}_0_result.pkl").exists()
    assert time.monotonic() - started < 240


@pytest.mark.slow
def test_a_ray_sweep_writes_results_csv(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    proc = _sweep(tmp_path, "hydra/launcher=ray_sweep", timeout=600)
    _assert_complete(proc, tmp_path)
