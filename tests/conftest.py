"""Test-suite configuration: the ``slow`` marker applied from one list.

``pytest -n 2 -q`` runs everything (what CI runs); ``pytest -n 2 -q -m "not slow"`` is the fast
subset for day-to-day work (CONTRIBUTING.md, "Tests"). A test is slow when it is listed in
``SLOW_TESTS`` below or carries ``@pytest.mark.slow`` itself. The list was chosen from a measured
run, ``python -m pytest -n 2 -q --durations=60 -p no:cacheprovider``, and names whole modules where
most of a module's cost is a shared fixture or every test solves a batch calibration;
``tests/test_docs_slow_list.py`` checks that every entry still names an existing test.
"""

from __future__ import annotations

import pytest

#: Node-id prefixes of the slow tests: a module (``tests/test_x.py``) or one test in it
#: (``tests/test_x.py::test_name``, every parametrisation included). Measured CPU time per test
#: on the shared machine in the comments (2026-11-28, ``--durations``, load 4-6 on 2 cores).
SLOW_TESTS: tuple[str, ...] = (
    # hypothesis: 50 random push sequences through the streaming filter (316 s under load)
    "tests/test_streaming_guards.py::test_any_push_sequence_succeeds_with_a_finite_state_or_raises_the_documented_error",
    # the observability boundary tables regenerated and compared with docs/observability.md (106 s)
    "tests/test_obs_docs.py::test_boundary_tables_match_a_fresh_run",
    "tests/test_obs_boundary.py",  # rank tests at Lie orders up to 4 (4 tests 8-19 s each)
    "tests/test_cli_conventions.py::test_tables_fit_80_columns",  # every verb at COLUMNS=80 (35 s)
    # batch calibration (GTSAM) on simulated and real logs: every test solves at least one graph
    "tests/test_calibrate_tags.py",
    "tests/test_calibrate_robust_loss.py",
    "tests/test_calibrate_sim.py",
    "tests/test_calibrate_survey_grouped.py",
    "tests/test_calibrate_survey_tags.py",
    "tests/test_calibrate_noise_scale.py",
    "tests/test_calibrate_covariance.py",
    "tests/test_calibrate_speed.py",
    "tests/test_calibrate_td_bias.py::test_time_offset_unbiased_at_a_low_imu_rate",
    "tests/test_calibrate_anchor_direction.py::test_anchor_side_bias_is_recovered",
    "tests/test_calibrate_direction.py::test_body_azimuth_bias_is_recovered_and_frees_the_lever_arm",
    "tests/test_calibrate_drift.py::test_injected_slow_bias_is_tracked_and_sigma_grows",
    "tests/test_range_error_oracle.py::test_removing_the_biases_improves_the_smoothed_trajectory",
    "tests/test_report_batch.py",  # a batch calibration as module fixture (12 s) and the CLI round trip
    # Monte Carlo through the process pool and a Dask LocalCluster
    "tests/test_mc_runner.py",
    "tests/test_mc_honesty.py::test_study_reports_every_quantity_against_its_bound",
    "tests/test_mc_seed_experiment.py::test_horizontal_anchor_plane_degrades_height_for_both_estimators",
    # the compiled filter pass against the Python loop on long logs
    "tests/test_filter_loop.py::test_compiled_pass_equals_python_loop_on_tdoa_with_pair_biases",
    "tests/test_filter_loop.py::test_compiled_pass_equals_python_loop_through_reopened_gates_and_divergence",
    "tests/test_eskf_tdoa.py::test_per_pair_tdoa_bias_is_recovered_and_others_stay_near_zero",
    # anchor placement examples run whole
    "tests/test_place_cli.py::test_room_example_discrete_stages_beat_both_baselines",
    "tests/test_place_cli.py::test_place_room_writes_outputs",
    # simulator integration against the truth, every trajectory kind
    "tests/test_sim_integration.py::test_ideal_imu_integrates_to_truth",
    "tests/test_sim_integration.py::test_ideal_imu_of_trajectory_file_integrates_to_truth",
    "tests/test_reproducibility.py::test_seed_ocp_cost",  # the seed OCP solved by IPOPT (10 s)
    # second pass, from the fast subset's own durations (python -m pytest -n 2 -q -m "not slow"
    # --durations=0 -p no:cacheprovider): the batch-calibration tests above 5 s and modules whose
    # fixtures solve a graph, the end-to-end CLI runs of calibrate and repeatability
    "tests/test_calibrate_anchor_loo.py",  # a surveyed graph as fixture (22 s) and leave-one-out re-solves
    "tests/test_calibrate_identifiability.py",
    "tests/test_calibrate_linear_split.py",
    "tests/test_calibrate_survey_sim.py",
    "tests/test_calibrate_anchor_direction.py",
    "tests/test_calibrate_anchors.py::test_gauge_convention_and_anchor_ranges_end_to_end",
    "tests/test_calibrate_frames.py::test_z_down_frame_and_known_bias_give_the_same_calibration",
    "tests/test_calibrate_direction.py::test_direction_with_drift_keeps_both_terms",
    "tests/test_calibrate_cli.py::test_calibrate_writes_its_files",
    "tests/test_calibrate_cli.py::test_repeatability_with_the_batch_method",
    "tests/test_calibrate_cli.py::test_estimate_anchors_option",
    "tests/test_calibrate_cli.py::test_repeatability_batch_takes_the_initialising_eskf_preset",
    "tests/test_clock_drift.py::test_clock_drift_detected_rate_recovered_and_handled",
    "tests/test_eval_repeatability.py::test_windows_on_the_executors_match_the_serial_run",
    "tests/test_report_html.py::test_report_repeatability_shows_the_per_window_bound",
    "tests/test_plan_proof.py::test_proof_runs_through_the_studies_executor_with_the_serial_numbers",
    "tests/test_cli_conventions.py::test_report_out_is_a_folder_and_html_a_file",
    "tests/test_obs_engine.py::test_vertical_anchor_line_is_yaw",
    "tests/test_obs_cli.py::test_structural_json_directions_are_name_vector_pairs",
    "tests/test_place_crane_readings.py::test_place_cli_draws_the_seed_layout_for_each_reading",
    "tests/test_measurement_models.py::test_altimeter_bias_is_estimated_and_height_tightens",
    "tests/test_measurement_models.py::test_user_model_with_finite_difference_jacobian_matches_builtin_height",
)


def is_listed(nodeid: str, listed: tuple[str, ...] = SLOW_TESTS) -> bool:
    """Whether ``nodeid`` is, or lies under, one of the ``listed`` node-id prefixes.

    A prefix matches the node id itself, its parametrisations (``prefix[...]``) and the tests
    under it (``prefix::...``), never a longer name (``test_x`` does not match ``test_x_other``).
    """
    return any(
        nodeid == p or nodeid.startswith(p + "::") or nodeid.startswith(p + "[") for p in listed
    )


def pytest_collection_modifyitems(config, items):
    for item in items:
        if is_listed(item.nodeid):
            item.add_marker(pytest.mark.slow)
