"""Seed 002 sec. IX in small: three anchors in one horizontal plane give a much
worse height than three anchors at different heights, for both estimators."""

import numpy as np
import pandas as pd

from uwbimu import studies as mc
from uwbimu.studies.examples import example_config


def test_horizontal_anchor_plane_degrades_height_for_both_estimators(tmp_path):
    d = example_config("seed-anchor-planes")
    for s in d["scenarios"]:
        s["scenario"]["duration"] = 20.0  # shorter than the example's 60 s to keep the test cheap
    cfg = mc.config_from_dict(d)
    summary = mc.run_study(cfg, tmp_path / "o", runs=3, workers=1, plots=True)
    df = pd.read_csv(tmp_path / "o" / "montecarlo.csv", dtype={"error": str})
    assert len(df) == 2 * 3 * 2
    assert (df["status"] == "ok").all(), df["error"].tolist()
    for est in ("pointmass", "eskf"):
        z = {sc: df[(df.scenario == sc) & (df.estimator == est)]["rmse_z"].to_numpy()
             for sc in ("different-heights", "horizontal-plane")}
        assert z["horizontal-plane"].min() > 2.0 * z["different-heights"].max(), (est, z)
        assert z["different-heights"].max() < 0.15, (est, z)
        # x and y stay good (the seed: "X and Y position estimation were good"): in every run with
        # anchors at different heights and for the point-mass EKF in both layouts; the 19-state ESKF
        # in the horizontal plane only in the median run (an ESKF run whose height runs away can
        # diverge and drag x, y along; 8 of 100 runs stop early in the 100-seed study, see docs)
        for sc in ("different-heights", "horizontal-plane"):
            xy = df[(df.estimator == est) & (df.scenario == sc)][["rmse_x", "rmse_y"]].to_numpy()
            if est == "eskf" and sc == "horizontal-plane":
                assert np.all(np.median(xy, axis=0) < 0.3), (est, sc, xy)
            else:
                assert np.all(xy < 0.3), (est, sc, xy)
    # the ESKF ran the full calibration (lever arm and time offset estimated)
    eskf = df[df.estimator == "eskf"]
    assert np.all(np.isfinite(eskf["lever_arm_err"])) and np.all(np.isfinite(eskf["time_offset_err"]))
    assert set(summary["figures"]) >= {"error_vs_time_pointmass.png", "error_vs_time_eskf.png", "nees.png",
                                       "position_vs_truth.png", "rmse_distribution.png"}
    assert (tmp_path / "o" / "position_vs_truth.png").stat().st_size > 10000
    # every run covers the flight or says it does not (coverage), and the summary counts cut runs
    assert df["coverage"].between(0.0, 1.0).all()
    assert (df[df.estimator == "pointmass"]["coverage"] > 0.98).all()
    for cell in summary["cells"]:
        assert cell["runs_truncated"] == int((df[(df.scenario == cell["scenario"])
                                                 & (df.estimator == cell["estimator"])]["coverage"] < 0.98).sum())
