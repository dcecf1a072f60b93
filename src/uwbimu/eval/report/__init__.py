"""One self-contained HTML calibration report for an estimator output folder.

:func:`write_report` reads what ``uwbimu estimate`` (and optionally
``uwbimu evaluate``, ``uwbimu repeatability`` and the observability analysis)
wrote into ``OUT`` and renders ``OUT/report.html``: every plot is an embedded
base64 PNG, there is no script and no external URL, so the file opens offline
and can be mailed as is.

Sections (``<section id=...>``; a section whose input is missing says so):

``calibration``    lever arm and time offset ± 1 sigma (and the documented/true
                   value with its z-score when known), IMU biases
``batch``          only for a ``uwbimu calibrate`` folder (:func:`is_batch_output`): t_d
                   profile, residual vs body-frame line-of-sight azimuth per anchor, anchor
                   2-sigma error ellipses, residuals without / with the range bias
``convergence``    lever arm and time offset over time with ±3 sigma bands
                   (``states.csv`` columns ``lx, ly, lz, time_offset`` + ``sd_*``, as ``uwbimu estimate`` writes them)
``residuals``      per-anchor innovation table: median, MAD, rejected %, flags
``nis``            histogram of the range NIS against the chi-square(1) density
``trajectory``     top view (and errors with ±3 sigma when ground truth exists)
``repeatability``  spread over windows vs predicted sigma (``repeatability.json``)
``observability``  excitation / observability timeline (``observability.csv``)
``warnings``       estimator warnings

Every summary a section states comes from one place (:mod:`.inputs`: the time-offset mode and verdict of
calibration.yaml's one schema and the run's events, the NIS summary of residuals.csv, the run's warnings) and the page
carries it as ``data-*`` attributes: ``#run-summary`` (``data-estimator``, ``data-td-mode``, ``data-td-verdict``,
``data-nis-*``, ``data-warnings``, ``data-warning-kinds``, ``data-out-dir``), each ``<section>`` its own (e.g.
``trajectory``: ``data-align``, ``data-band``, ``data-position-rmse``, ``data-outside-band-pct``), each warning
``data-warning-kind``. Figures follow the one rounding rule of :mod:`uwbimu.formatting`; anchors the natural order.

The package: :mod:`.common` (templates, tables, figures), :mod:`.inputs` (what is read, shared summaries),
:mod:`.sections` (the sections), :mod:`.batch` (the ``uwbimu calibrate`` section), :mod:`.render` (the page).
"""

from uwbimu.eval.report.batch import BATCH_FILES, error_ellipse, is_batch_output, line_of_sight_azimuth
from uwbimu.eval.report.common import CAL_COLUMNS, SECTION_TITLES, figure_data_uri
from uwbimu.eval.report.inputs import ReportInputs
from uwbimu.eval.report.render import SECTIONS, render_report, write_report
from uwbimu.eval.report.sections import anchor_residual_table

__all__ = ["BATCH_FILES", "CAL_COLUMNS", "ReportInputs", "SECTIONS", "SECTION_TITLES", "anchor_residual_table",
           "error_ellipse", "figure_data_uri", "is_batch_output", "line_of_sight_azimuth", "render_report",
           "write_report"]
