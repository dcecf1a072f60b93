"""Radio model: Friis budget, antenna patterns, CSV import errors, ray casting, fast kernels."""

import numpy as np
import pytest

from uwbimu.design.radio import (
    RANGE_PRESETS,
    Bar,
    Box,
    CosN,
    LinkModel,
    Omni,
    PatternError,
    count_links_fast,
    count_links_grid,
    fspl_db,
    k_coverage,
    load_pattern_csv,
    lobe_sphere,
    to_soa,
)


def test_fspl_friis_values():
    f = 6.4896e9
    assert fspl_db(1.0, f) == pytest.approx(20 * np.log10(4 * np.pi * f / 299_792_458.0))
    assert fspl_db(20.0, f) - fspl_db(10.0, f) == pytest.approx(20 * np.log10(2))


@pytest.mark.parametrize("preset", sorted(RANGE_PRESETS))
def test_omni_link_closes_exactly_within_preset_range(preset):
    lm = LinkModel.from_preset(preset)
    R = RANGE_PRESETS[preset]
    pts = np.array([[0.99 * R, 0, 0], [1.01 * R, 0, 0]])
    links = lm.links(pts, np.zeros((1, 3)))
    assert links[:, 0].tolist() == [True, False]


def test_unknown_preset_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown radio preset"):
        LinkModel.from_preset("nope")


def test_cosn_half_power_beamwidth_and_directivity():
    p = CosN(beamwidth_deg=60.0)
    g = p.gain_cos(np.cos(np.radians([0.0, 30.0])))
    assert g[0] - g[1] == pytest.approx(10 * np.log10(2), abs=1e-9)
    assert p.peak_dbi == pytest.approx(10 * np.log10(2 * (p.n + 1)))
    assert p.gain_cos(np.array([-0.5]))[0] == pytest.approx(p.peak_dbi - p.front_to_back_db)
    # reach along the boresight scales with 10^(G/20)
    lm = LinkModel(max_range=10.0, anchor_pattern=p)
    r_pk = 10.0 * 10 ** (p.peak_dbi / 20)
    pts = np.array([[0.0, 0, -0.99 * r_pk], [0, 0, -1.01 * r_pk]])
    assert lm.links(pts, np.zeros((1, 3)), np.array([[0, 0, -1.0]]))[:, 0].tolist() == [True, False]
    with pytest.raises(PatternError):
        CosN(beamwidth_deg=200)


def _write_pattern(path, az, el, fn):
    lines = ["azimuth_deg,elevation_deg,gain_dbi"]
    for e in el:
        for a in az:
            lines.append(f"{a},{e},{fn(a, e):.6f}")
    path.write_text("\n".join(lines) + "\n")


def test_table_pattern_matches_cosn(tmp_path):
    cos = CosN(90.0)
    az = np.arange(-180, 180, 5.0)
    el = np.arange(-90, 91, 5.0)

    def fn(a, e):
        d = np.array([np.cos(np.radians(e)) * np.cos(np.radians(a)), np.cos(np.radians(e)) * np.sin(np.radians(a)),
                      np.sin(np.radians(e))])
        return float(cos.gain_local(d[None])[0])

    f = tmp_path / "pat.csv"
    _write_pattern(f, az, el, fn)
    tab = load_pattern_csv(f)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    front = d[:, 0] > 0.2  # away from the cos^n kink at 90 deg
    assert np.allclose(tab.gain_local(d[front]), cos.gain_local(d[front]), atol=0.25)
    # a table-pattern link model works through the general (NumPy) path
    lm = LinkModel(max_range=10.0, anchor_pattern=tab)
    assert lm.links(np.array([[0, 0, -5.0]]), np.zeros((1, 3)), np.array([[0, 0, -1.0]]))[0, 0]
    with pytest.raises(ValueError, match="axisymmetric"):
        lm.reach_lut()


@pytest.mark.parametrize(
    "text, match",
    [
        ("az,el,g\n0,0,1\n", "missing column"),
        ("azimuth_deg,elevation_deg,gain_dbi\n0,0,1\n10,0,abc\n", "line 3, column 'gain_dbi'"),
        ("azimuth_deg,elevation_deg,gain_dbi\n0,0,1\n0,0,2\n10,0,1\n10,10,1\n0,10,1\n", "duplicate"),
        ("azimuth_deg,elevation_deg,gain_dbi\n0,0,1\n10,0,1\n0,10,1\n", "incomplete"),
        ("azimuth_deg,elevation_deg,gain_dbi\n0,95,1\n", "elevation_deg"),
    ],
)
def test_pattern_csv_errors_name_file_and_line(tmp_path, text, match):
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(PatternError, match=match) as ei:
        load_pattern_csv(f)
    assert "bad.csv" in str(ei.value)


def test_box_ray_casting():
    box = Box((4, -1, -1), (5, 1, 1))
    o = np.zeros(3)
    targets = np.array([[10, 0, 0], [3, 0, 0], [10, 5, 0], [10, 0.05, 0]], float)
    assert box.hits(o, targets).tolist() == [True, False, False, True]


def test_bar_ray_casting_matches_dense_sampling():
    rng = np.random.default_rng(1)
    bar = Bar((0, -3, 2), (0, 3, 2), radius=0.3)
    o = np.array([-4.0, 0.3, 1.0])
    targets = rng.uniform([2, -4, 0], [6, 4, 4], (300, 3))
    s = np.linspace(0, 1, 4001)
    brute = np.array([np.min(bar.distance(o + s[:, None] * (t - o))) <= 0.3 for t in targets])
    got = bar.hits(o, targets)
    # disagreements only from the sampling resolution at grazing incidence
    assert np.mean(got == brute) > 0.99
    assert got.any() and (~got).any()


def test_nlos_loss_shrinks_reach_and_own_mount_is_ignored():
    wall = Box((4, -5, -5), (4.2, 5, 5), loss_db=10.0)
    lm = LinkModel(max_range=10.0, obstacles=[wall])
    pts = np.array([[0.99 * 10 * 10 ** (-10 / 20), 0, 0], [6.0, 0, 0]])
    a = np.array([[0.0, 0.0, 0.0]])
    # through the wall, the reach is 10 m * 10^(-10/20) = 3.16 m from the anchor
    assert lm.links(pts, a)[:, 0].tolist() == [True, False]
    assert lm.margin_db(pts, a)[1, 0] == pytest.approx(lm.budget_db - fspl_db(6.0) - 10.0)
    # an anchor mounted inside the obstacle does not shadow itself
    a_in = np.array([[4.1, 0.0, 0.0]])
    assert lm.links(np.array([[8.0, 0, 0]]), a_in)[0, 0]


def test_fast_kernels_match_reference_links():
    rng = np.random.default_rng(7)
    lm = LinkModel(max_range=6.0, anchor_pattern=CosN(100.0))
    axes = (np.arange(0.5, 12, 1.0), np.arange(0.5, 15, 1.0), np.arange(0.25, 8, 0.5))
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    anchors = rng.uniform([0, 0, 0], [12, 15, 8], (9, 3))
    bores = rng.normal(size=(9, 3))
    bores /= np.linalg.norm(bores, axis=1, keepdims=True)
    ref = lm.links(pts, anchors, bores, ray_cast=False)
    lut = lm.reach_lut()
    c_grid = count_links_grid(axes, anchors, bores, lut)
    c_pts = count_links_fast(to_soa(pts), anchors, bores, lut)
    c_ref = ref.sum(axis=1)
    # float32 + LUT interpolation: identical except possibly at the exact reach boundary
    assert np.mean(c_grid == c_ref) > 0.999
    assert np.mean(c_pts == c_ref) > 0.999
    margin = lm.margin_db(pts, anchors, bores, ray_cast=False)
    bad = np.flatnonzero(c_grid != c_ref)
    assert np.all(np.min(np.abs(margin[bad]), axis=1) < 0.05)
    assert np.array_equal(k_coverage(ref, 3), c_ref >= 3)


def test_lobe_sphere_contains_the_reach_lobe():
    lm = LinkModel(max_range=10.0, anchor_pattern=CosN(90.0))
    lut = lm.reach_lut()
    m, rho = lobe_sphere(lut)
    c = np.linspace(-1, 1, len(lut))
    r = np.sqrt(lut)
    pts = np.column_stack([r * c, r * np.sqrt(1 - c**2)])
    assert np.all(np.hypot(pts[:, 0] - m, pts[:, 1]) <= rho)
    assert rho < lm.peak_range  # tighter than the peak-range sphere
    assert Omni(3.0).peak_dbi == 3.0
