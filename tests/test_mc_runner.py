"""Monte Carlo runner: local pool vs a real Dask LocalCluster (bit-identical),
resume after interruption, config-mismatch refusal, failed runs kept, metrics."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from uwbimu.errors import OutputError  # a refused study folder: exit 4, the output rule
import yaml
from typer.testing import CliRunner

from uwbimu.estimation.result import EstimationResult
from uwbimu import studies as mc
from uwbimu.studies.examples import example_config
from uwbimu.io.dataset import Dataset, DatasetMeta

REPO = Path(__file__).resolve().parents[1]

# Short, cheap flights: the point of these tests is the machinery, not accuracy.
CFG = {
    "name": "t",
    "runs": 4,
    "seed_base": 11,
    "chunk_size": 2,
    "trace_rate_hz": 2.0,
    "scenarios": [
        {"name": "circ", "builtin": "circle",
         "overrides": {"duration": 6.0, "imu": {"rate_hz": 100.0}, "uwb": {"rate_hz": 25.0}}},
        {"name": "fig8", "builtin": "figure8",
         "overrides": {"duration": 6.0, "imu": {"rate_hz": 100.0}, "uwb": {"rate_hz": 25.0}}},
    ],
    "estimators": [{"name": "pm", "kind": "pointmass", "options": {"yaw_window": 4.0}}],
}


def _cfg(**over):
    d = json.loads(json.dumps(CFG))
    d.update(over)
    return mc.config_from_dict(d)


def _table(out):
    return pd.read_csv(Path(out) / "montecarlo.csv", dtype={"error": str})


def _traces(out):
    res = {}
    for f in sorted((Path(out) / mc.CHUNK_DIR).glob("*.npz")):
        with np.load(f) as z:
            for r, run in enumerate(z["runs"]):
                res[(f.name.split("__")[0], int(run))] = (z["err"][r], z["nees"][r])
    return res


@pytest.fixture(scope="module")
def pool_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("mc") / "pool"
    summary = mc.run_study(_cfg(), out, workers=2, plots=False)
    return out, summary


def test_pool_run_writes_one_row_per_run_with_distinct_seeds(pool_run):
    out, summary = pool_run
    df = _table(out)
    assert len(df) == 2 * 4 * 1
    assert (df["status"] == "ok").all(), df["error"].tolist()
    assert df.groupby("scenario")["seed_noise"].nunique().eq(4).all()
    # paired design: run i has the same seeds in every scenario
    s = df.pivot(index="run", columns="scenario", values="seed_noise")
    assert (s["circ"] == s["fig8"]).all()
    assert np.all(np.isfinite(df[["rmse_x", "rmse_y", "rmse_z", "nees_pos_mean"]].to_numpy()))
    assert df["rmse_3d"].max() < 1.0
    cell = summary["cells"][0]
    assert cell["runs"] == 4 and cell["failed"] == 0 and cell["rmse_x"]["n"] == 4
    assert summary["execution"]["backend"] == "process-pool"
    assert json.loads((out / "summary.json").read_text())["cells"][0]["scenario"] == "circ"


def test_dask_localcluster_gives_bit_identical_results_even_when_a_worker_dies(pool_run, tmp_path):
    import os

    from distributed import Client, LocalCluster

    out_pool, _ = pool_run
    killed = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:

        def die_soon():
            import threading

            threading.Timer(0.2, os._exit, args=(1,)).start()  # the worker process dies hard

        def kill_a_worker_after_first_chunk(done, total):
            if done > 0 and not killed:
                # the client's view of the workers can be momentarily empty on a loaded machine (seen once
                # under pytest -n 2): then kill at a later chunk
                workers = sorted(client.scheduler_info()["workers"])
                if not workers:
                    return
                client.run(die_soon, workers=[workers[0]])
                killed.append(workers[0])

        # chunks of one run (chunking does not change results) so that tasks are in flight when it dies
        # through the scheduler address, as `--scheduler ADDRESS` does (its own client)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(os, "cpu_count", lambda: 7)  # this machine's size must not matter with a scheduler
            summary = mc.run_study(_cfg(chunk_size=1), tmp_path / "dask", scheduler=cluster.scheduler_address,
                                   plots=False, progress=kill_a_worker_after_first_chunk)
    assert killed and summary["execution"]["backend"] == "dask"
    assert summary["execution"]["workers"] == 2  # the cluster's size, not this machine's core count
    assert summary["execution"]["task_failures"] == []
    diffs = list(mc.iter_rows_equal_ignoring_timing(_table(out_pool), _table(tmp_path / "dask")))
    assert diffs == []
    a, b = _traces(out_pool), _traces(tmp_path / "dask")
    assert a.keys() == b.keys() and len(a) == 8
    for k in a:
        np.testing.assert_array_equal(a[k][0], b[k][0])
        np.testing.assert_array_equal(a[k][1], b[k][1])


def test_resume_after_interruption_skips_finished_runs(pool_run, tmp_path):
    out = tmp_path / "resume"
    calls = []

    def interrupt_after_first_chunk(done, total):
        calls.append(done)
        if done >= 2:
            raise KeyboardInterrupt  # the user hits Ctrl-C after one chunk is on disk

    with pytest.raises(KeyboardInterrupt):
        mc.run_study(_cfg(), out, workers=1, progress=interrupt_after_first_chunk, plots=False)
    assert len(list((out / mc.CHUNK_DIR).glob("*.csv"))) == 1
    # debris of a crash mid-write: a temporary file and traces whose rows never landed
    (out / mc.CHUNK_DIR / ".circ__000002-000003__2.csv.tmp123.csv").write_text("scenario,run\ncirc,2\n")
    orphan = next((out / mc.CHUNK_DIR).glob("*.npz"))
    (out / mc.CHUNK_DIR / "circ__000002-000002__1.npz").write_bytes(orphan.read_bytes())
    summary = mc.run_study(_cfg(), out, workers=1, plots=True)
    assert summary["execution"]["runs_resumed_from_disk"] == 2
    assert summary["execution"]["tasks_this_call"] == 3
    assert list(mc.iter_rows_equal_ignoring_timing(_table(pool_run[0]), _table(out))) == []
    for fig in ("rmse_distribution.png", "nees.png", "error_vs_time_pm.png"):
        assert (out / fig).stat().st_size > 1000
    # a second rerun has nothing left to do, and more runs extend the study
    again = mc.run_study(_cfg(), out, workers=1, plots=False)
    assert again["execution"]["tasks_this_call"] == 0
    more = mc.run_study(_cfg(), out, runs=5, workers=1, plots=False)
    assert more["execution"]["runs_resumed_from_disk"] == 8
    assert len(_table(out)) == 10


def test_config_mismatch_is_refused(tmp_path):
    out = tmp_path / "o"
    mc.run_study(_cfg(runs=1), out, workers=1, plots=False)
    with pytest.raises(OutputError, match="different study configuration.*seed_base"):
        mc.run_study(_cfg(runs=1, seed_base=12), out, workers=1, plots=False)
    bad = json.loads(json.dumps(CFG))
    bad["scenarios"][0]["overrides"]["uwb"]["sigma"] = 0.2
    with pytest.raises(OutputError, match=r"scenarios\[0\].scenario.uwb.sigma"):
        mc.run_study(mc.config_from_dict(bad), out, workers=1, plots=False)
    # the CLI refuses with a readable message and a non-zero exit code
    from uwbimu.cli.main import app

    cfg_file = tmp_path / "study.yaml"
    cfg_file.write_text(yaml.safe_dump({**CFG, "seed_base": 99}))
    res = CliRunner().invoke(app, ["montecarlo", str(cfg_file), "--out", str(out), "--runs", "1", "--workers", "1"])
    assert res.exit_code == 4  # output refused (the output rule)
    assert "different study configuration" in res.output
    # a folder that is not a study output is never written into
    other = tmp_path / "other"
    other.mkdir()
    (other / "precious.txt").write_text("keep")
    with pytest.raises(OutputError, match="not empty"):
        mc.run_study(_cfg(runs=1), other, workers=1, plots=False)
    with pytest.raises(OutputError, match="is a file"):
        mc.run_study(_cfg(runs=1), other / "precious.txt", workers=1, plots=False)
    assert (other / "precious.txt").read_text() == "keep"


def test_cli_runs_a_study_and_failed_runs_are_kept(tmp_path):
    from uwbimu.cli.main import app

    cfg = json.loads(json.dumps(CFG))
    cfg["scenarios"] = cfg["scenarios"][:1]
    cfg["estimators"].append({"name": "broken", "kind": "pointmass", "options": {"no_such_option": 1}})
    f = tmp_path / "study.yaml"
    f.write_text(yaml.safe_dump(cfg))
    res = CliRunner().invoke(app, ["montecarlo", str(f), "--out", str(tmp_path / "o"), "--runs", "2",
                                   "--workers", "1", "--no-plots"])
    assert res.exit_code == 0, res.output
    df = _table(tmp_path / "o")
    assert len(df) == 4
    broken = df[df["estimator"] == "broken"]
    assert (broken["status"] == "failed").all() and broken["error"].str.contains("no_such_option").all()
    assert (df[df["estimator"] == "pm"]["status"] == "ok").all()
    assert "run(s) failed" in res.output


def test_config_errors_name_the_field(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump({**CFG, "estimators": [{"name": "x", "kind": "kalman"}]}))
    with pytest.raises(mc.MonteCarloError, match=r"(?s)bad.yaml.*estimators.0.kind"):
        mc.load_config(f)
    dup = {**CFG, "estimators": CFG["estimators"] * 2}
    with pytest.raises(mc.MonteCarloError, match="duplicate estimator names"):
        mc.config_from_dict(dup)
    with pytest.raises(mc.MonteCarloError, match="exactly one of builtin, file, scenario"):
        mc.config_from_dict({**CFG, "scenarios": [{"name": "a"}]})


def test_metrics_on_a_known_error():
    t = np.linspace(0.0, 10.0, 101)
    gt = pd.DataFrame({"t": t, "px": t, "py": 0 * t, "pz": 0 * t + 1, "qw": 1.0, "qx": 0.0, "qy": 0.0, "qz": 0.0})
    ds = Dataset(imu=pd.DataFrame(), uwb=pd.DataFrame(), anchors=pd.DataFrame(), groundtruth=gt,
                 meta=DatasetMeta(truth={"lever_arm": [0.1, 0.0, 0.0], "time_offset": 0.02}))
    states = np.zeros((101, 20))
    states[:, 0] = t + 0.3
    states[:, 1] = 0.0
    states[:, 2] = 1.0 - 0.4
    sd = np.full((101, 19), np.nan)
    sd[:, 0:3] = [0.3, 1.0, 0.4]
    cov = np.full((101, 19, 19), np.nan)
    cov[:, 0:3, 0:3] = np.diag([0.09, 1.0, 0.16])
    res = EstimationResult(t=t, states=states, sd=sd, residuals=pd.DataFrame(), covariances=cov,
                           calibration={"lever_arm": [0.13, 0.0, 0.04], "lever_arm_sd": [0.01] * 3,
                                        "time_offset": 0.025, "time_offset_sd": 0.001})
    row, trace = mc.run_metrics(res, ds)
    assert row["rmse_x"] == pytest.approx(0.3) and row["rmse_y"] == 0 and row["rmse_z"] == pytest.approx(0.4)
    assert row["rmse_3d"] == pytest.approx(0.5)
    assert row["nees_pos_mean"] == pytest.approx(2.0) and row["nees_kind"] == "full"
    assert row["lever_arm_err"] == pytest.approx(0.05)
    assert row["time_offset_err"] == pytest.approx(0.005)
    # an estimator that keeps the lever arm fixed (sd NaN) reports no lever-arm error
    res.calibration["lever_arm_sd"] = [float("nan")] * 3
    res.covariances = None
    row2, _ = mc.run_metrics(res, ds, skip_initial_s=5.0)
    assert "lever_arm_err" not in row2 and row2["n_samples"] == 51 and row2["nees_kind"] == "diag"


def test_example_yaml_is_the_builtin_example_and_seeds_are_stable():
    f = REPO / "examples" / "montecarlo" / "seed_anchor_planes.yaml"
    assert yaml.safe_load(f.read_text()) == example_config("seed-anchor-planes")
    cfg = mc.load_config(REPO / "examples" / "montecarlo" / "quick_study.yaml")
    assert [s.name for s in cfg.scenarios] == ["figure8-30s", "circle-room4"]
    assert mc.run_seeds(0, 0) == mc.run_seeds(0, 0) != mc.run_seeds(0, 1)
    assert len({mc.run_seeds(5, i) for i in range(200)}) == 200
