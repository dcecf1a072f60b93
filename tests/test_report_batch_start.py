"""The report's "Start and held blocks" part of a ``uwbimu calibrate`` folder (issue 27 item 4): where the batch
started (calibration.yaml ``start``) and which blocks it held (``held_at_prior``), as data attributes."""

from __future__ import annotations

import re
from types import SimpleNamespace

from uwbimu.eval.report.batch import _batch_start_part


def _attrs(html: str) -> dict:
    tag = re.search(r'<div class="part"[^>]*>', str(html)).group(0)
    return dict(re.findall(r'data-([a-z-]+)="([^"]*)"', tag))


def test_eskf_start_without_held_blocks():
    a = _attrs(_batch_start_part(SimpleNamespace(calibration={"start": {"source": "eskf", "reason": "healthy"}})))
    assert a == {"part": "start", "source": "eskf", "reason": "healthy", "held": ""}


def test_multilateration_start_with_held_blocks_is_a_warning():
    cal = {"start": {"source": "multilateration", "reason": "diverged+multilateration"},
           "held_at_prior": {"blocks": ["anchor_bias", "lever_arm"]}}
    html = str(_batch_start_part(SimpleNamespace(calibration=cal)))
    a = _attrs(html)
    assert a["source"] == "multilateration" and a["reason"] == "diverged+multilateration"
    assert a["held"] == "anchor_bias lever_arm"
    assert "warn" in html


def test_older_output_without_start_says_unknown():
    assert _attrs(_batch_start_part(SimpleNamespace(calibration={})))["source"] == "unknown"
