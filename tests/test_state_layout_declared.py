"""State blocks declared once (issue 31 item 1): the declarations of ``models/blocks.py`` compile into the
layout's slices and the kernels' process-noise tables; no kernel infers a block from an array length or
a literal; a new block is one declaration plus its Jacobian columns (pinned by ``fd_jacobian``)."""

from __future__ import annotations

import ast
import inspect
import itertools
import math

import numpy as np
import pytest

from uwbimu.estimation import kernels as K
from uwbimu.estimation.options import EskfOptions
from uwbimu.estimation.outputs import block_calibration
from uwbimu.estimation.problem import block_counts, block_process_noise, make_settings
from uwbimu.models import blocks as B
from uwbimu.models import kernels as MK
from uwbimu.models import state as S
from uwbimu.models.imu import ImuNoise
from uwbimu.models.measurements import HeightModel, MeasurementModel, fd_jacobian
from uwbimu.models.state import StateLayout

COUNTS = [dict(n_anchor_bias=a, n_height_bias=h, n_tags=t, n_pair_bias=p)
          for a, h, t, p in itertools.product((0, 4), (0, 1), (1, 3), (0, 5))]


def _rand_state(rng, L):
    x = rng.normal(size=L.n_nom)
    x[S.Q] /= np.linalg.norm(x[S.Q])
    return x


@pytest.mark.parametrize("counts", COUNTS)
def test_blocks_are_contiguous_in_declaration_order_and_nominal_is_shifted_uniformly(counts):
    L = StateLayout(**counts)
    e = n = 0
    for b in B.BLOCKS:
        c = L.count[b.name]
        se, sn = L.err(b.name), L.nom("q" if b.name == "theta" else b.name)
        assert (se.start, se.stop, sn.start, sn.stop) == (e, e + c * b.size, n, n + c * b.n_nom), b.name
        if c and B.BLOCKS.index(b) > B.BLOCKS.index(B.BLOCK["theta"]):
            assert sn.start - se.start == S.NOM_SHIFT == 1, b.name  # the kernels' x[i + NOM_SHIFT]
        e, n = se.stop, sn.stop
    assert (L.n_err, L.n_nom) == (e, n)
    assert L.count["anchor_bias"] == counts["n_anchor_bias"] and L.n_tags == counts["n_tags"]
    # the base 19 / 20 and the kernels' constants come from the same declarations
    assert (S.ERROR_DIM, S.NOMINAL_DIM, S.E_L, S.E_TD, S.N_TD, S.N_DYN) == (19, 20, 15, 18, 19, 15)
    assert [L.lever_err(i).start for i in range(L.n_tags)] == [15] + list(
        range(L.err("extra_levers").start, L.err("extra_levers").stop, 3))


@pytest.mark.parametrize("counts", COUNTS)
def test_process_noise_tables_are_the_layout_slices_of_the_non_imu_blocks(counts):
    L = StateLayout(**counts)
    vals = {"lever": (1.0, 0.0), "t_d": (2.0, 0.0), "anchor_bias": (3.0, 0.5), "extra_levers": (4.0, 0.0),
            "height_bias": (5.0, 0.0)}
    pn = L.process_noise(np.arange(4.0), vals)
    rows = [b for b in L.blocks if b.process_noise != "imu"]
    assert [b.kind for b in rows] == pn.kind.tolist()
    for i, b in enumerate(rows):
        se, sn = L.err(b.name), L.nom(b.name)
        assert (pn.err0[i], pn.nom0[i], pn.size[i]) == (se.start, sn.start, se.stop - se.start)
        assert pn.q[i] == vals.get(b.name, (0.0, 0.0))[0]
    assert pn.kind.dtype == pn.err0.dtype == np.int64 and pn.q.dtype == np.float64
    with pytest.raises(ValueError):
        L.process_noise(np.zeros(4), {})  # a random-walk block without its noise is an error, not zero


def test_output_names_are_unique():
    assert len(set(S.ERROR_STATE_NAMES)) == len(S.ERROR_STATE_NAMES) == S.ERROR_DIM
    assert len(set(S.NOMINAL_STATE_NAMES)) == len(S.NOMINAL_STATE_NAMES) == S.NOMINAL_DIM
    for b in B.BLOCKS:
        assert len(set(b.output_names)) == b.size and len(set(b.nom_names)) == b.n_nom
    keys = [b.output_key for b in B.BLOCKS if b.output_key]
    assert len(set(keys)) == len(keys) and set(B.OUTPUT_ORDER) == {b.name for b in B.BLOCKS if b.output_key}
    names = StateLayout(3, 1, 2, 2).error_names()
    assert len(set(names)) == len(names) == StateLayout(3, 1, 2, 2).n_err
    with pytest.raises(ValueError):
        B.BlockSpec("bad", 2, "one", "constant", ("a",), "m")  # one output name per component


def _code_constants(module, value):
    """Integer literals ``value`` in the module's code (docstrings excluded)."""
    tree = ast.parse(inspect.getsource(module))
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and type(n.value) is int
            and n.value == value]


@pytest.mark.parametrize("module", [MK, K])
def test_kernels_infer_no_block_from_an_array_length_or_a_literal(module):
    src = inspect.getsource(module)
    assert "noise.shape" not in src and "len(noise)" not in src
    assert "pn.shape" not in src  # the tables say which blocks there are, never their lengths alone
    # the lever arm's offset (15) and the first extra's (19) are layout constants, never literals
    assert _code_constants(module, 15) == [] and _code_constants(module, 19) == []
    tree = ast.parse(src)
    # no "+ 1" from an error index to a nominal one: those go through NOM_SHIFT
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.BinOp):
            idx = node.slice
            if isinstance(idx.right, ast.Constant) and isinstance(idx.left, ast.Name):
                assert not (idx.left.id.startswith(("bias", "pair", "lever")) and idx.right.value == 1), \
                    ast.unparse(node)


def _legacy_process_noise(P, dt, noise):
    """The process-noise step as the kernels did it before the declarations (positional ``noise`` read by
    its length), operation for operation: the tables must reproduce it bit for bit."""
    N = P.shape[0]
    adt = abs(dt)
    for i in range(3):
        P[i, i] += noise[0] * adt**3 / 3.0
        P[i, 3 + i] += noise[0] * adt**2 / 2.0
        P[3 + i, i] += noise[0] * adt**2 / 2.0
        P[3 + i, 3 + i] += noise[0] * adt
        P[6 + i, 6 + i] += noise[1] * adt
        P[9 + i, 9 + i] += noise[2] * adt
        P[12 + i, 12 + i] += noise[3] * adt
        P[15 + i, 15 + i] += noise[4] * adt
    P[18, 18] += noise[5] * adt
    n_gm = int(noise[8]) if len(noise) >= 9 else N - 19
    if len(noise) >= 8 and noise[7] > 0.0 and n_gm > 0:
        f = math.exp(-adt * noise[7])
        for r in range(19, 19 + n_gm):
            for c in range(N):
                P[r, c] *= f
                P[c, r] *= f
            P[r, r] += noise[6] * (1.0 - f * f)
    if len(noise) >= 10:
        n_lev = int(noise[10]) if len(noise) >= 11 else 0
        r0 = 19 + int(noise[8]) + (int(noise[11]) if len(noise) >= 12 else 0)
        for r in range(r0, r0 + n_lev):
            P[r, r] += noise[4] * adt
        for r in range(r0 + n_lev, N):
            P[r, r] += noise[9] * adt


@pytest.mark.parametrize("counts", COUNTS)
def test_declared_process_noise_is_bit_identical_to_the_positional_vector(counts):
    rng = np.random.default_rng(sum(counts.values()))
    opts = EskfOptions(anchor_bias={"mode": "estimate", "correlation_time": 7.0}, lever_arm={"random_walk": 3e-3},
                       time_offset={"random_walk": 2e-4}, height={"bias_random_walk": 0.02})
    L = StateLayout(**counts)
    imu = np.array([4e-4, 3e-5, 1e-6, 1e-8])
    pn = L.process_noise(imu, block_process_noise(opts, L))
    nb, nh, n_lev, n_pair = L.n_anchor_bias, L.n_height_bias, 3 * (L.n_tags - 1), L.n_pair_bias
    legacy = list(imu) + [3e-3**2, 2e-4**2]
    gm = [0.1**2, 1.0 / 7.0] if nb else [0.0, 0.0]
    if nh or n_lev or n_pair:
        legacy += gm + [float(nb), 0.02**2, float(n_lev), float(n_pair)]
    elif nb:
        legacy += gm
    A = rng.normal(size=(L.n_err, L.n_err))
    for dt in (2e-3, -1e-3, 0.25):
        P0 = A @ A.T
        P1, P2 = P0.copy(), P0.copy()
        MK._add_process_noise(P1, dt, pn)
        _legacy_process_noise(P2, dt, np.array(legacy))
        assert np.array_equal(P1, P2)
    x = rng.normal(size=L.n_nom)
    x1, x2 = x.copy(), x.copy()
    MK.decay_biases(x1, 0.3, pn)
    x2[L.nom("anchor_bias")] *= math.exp(-0.3 / 7.0)
    assert np.array_equal(x1, x2)


def test_make_settings_compiles_counts_noise_mask_and_priors_from_the_declarations():
    opts = EskfOptions(anchor_bias={"mode": "consider", "prior_sd": 0.2}, height={"bias": "estimate"},
                       tdoa_pair_bias={"mode": "estimate", "prior_sd": 0.07}, lever_arm={"mode": "fixed"})
    noise = ImuNoise(accel_noise_density=0.01, gyro_noise_density=1e-3, accel_bias_rw=1e-4, gyro_bias_rw=1e-5)
    anchors = np.arange(12.0).reshape(4, 3)
    prob, pr = make_settings(opts, list("abcd"), anchors, noise, 0.1, None, [0, 0, 0.1], ["t1", "t2"],
                             [(0, 1), (2, 3)])
    L = prob.layout
    assert L.count == {**{b.name: 1 for b in B.BLOCKS if b.multiplicity == "one"}, "anchor_bias": 4,
                       "pair_bias": 2, "extra_levers": 1, "height_bias": 1}
    assert block_counts(opts, 4, 2, 2) == {k: v for k, v in L.count.items() if B.BLOCK[k].multiplicity != "one"}
    mask = prob.gain_mask
    assert not mask[L.err("anchor_bias")].any() and not mask[L.err("lever")].any()
    assert not mask[L.err("extra_levers")].any() and mask[L.err("pair_bias")].all() and mask[L.err("t_d")].all()
    assert pr.block_sd == {"anchor_bias": 0.2, "pair_bias": 0.07, "height_bias": 1.0}
    assert (prob.pair_sd0, prob.height_sd0) == (0.07, 1.0)
    with pytest.raises(TypeError):  # one name per quantity: the typed fields, no legacy mapping keys
        pr["td_sd"]
    assert prob.bias_idx.tolist() == list(range(L.err("anchor_bias").start, L.err("anchor_bias").stop))
    pn = prob.process_noise
    row = {int(e): i for i, e in enumerate(pn.err0)}
    hb = row[L.err("height_bias").start]
    assert pn.kind[hb] == B.PN_RANDOM_WALK and pn.q[hb] == opts.height.bias_random_walk**2
    assert pn.kind[row[L.err("pair_bias").start]] == B.PN_CONSTANT


def test_calibration_outputs_loop_over_the_declared_blocks():
    L = StateLayout(2, 1, 1, 1)
    rng = np.random.default_rng(3)
    x, sd = _rand_state(rng, L), rng.uniform(0.1, 1.0, L.n_err)
    opts = EskfOptions(anchor_bias={"mode": "estimate"}, time_offset={"mode": "fixed"})
    cal = block_calibration(L, x, sd, opts, ["A", "B"], {(0, 1): L.err("pair_bias").start})
    assert list(cal) == ["lever_arm", "lever_arm_sd", "lever_arm_mode", "time_offset", "time_offset_sd",
                         "time_offset_mode", "accel_bias", "accel_bias_sd", "gyro_bias", "gyro_bias_sd",
                         "anchor_bias", "anchor_bias_sd", "anchor_bias_mode", "tdoa_pair_bias",
                         "tdoa_pair_bias_sd", "height_bias", "height_bias_sd"]
    assert cal["time_offset"] == x[S.TD] and cal["time_offset_sd"] == 0.0  # fixed: no sd
    assert cal["anchor_bias"]["B"] == x[L.nom("anchor_bias")][1] and cal["anchor_bias_sd"]["A"] == sd[19]
    assert cal["tdoa_pair_bias"] == {"A-B": x[L.nom("pair_bias")][0]}
    assert cal["height_bias"] == x[L.nom("height_bias")][0]


# --- a new block: one declaration plus its Jacobian columns --------------------------------------------

#: a barometer scale factor (a second altimeter state next to ``height_bias``): declared once here
BARO_SCALE = B.BlockSpec("baro_scale", 1, "optional", "random_walk", ("hs",), "1",
                         noise_option=("height.bias_random_walk",), enabled_by=("height.bias", ("estimate",)),
                         prior_sd_option="height.bias_prior_sd", output_key="baro_scale",
                         doc="altimeter scale error: measured height (1 + s) p_z + b")


class ScaledHeight(MeasurementModel):
    """Height with bias and scale; its Jacobian columns are the only code the new block needs."""

    dim, clock, name = 1, "imu", "scaled-height"

    def __init__(self, layout):
        self.ib, self.js = layout.nom("height_bias").start, layout.nom("baro_scale").start
        self.eb, self.es = layout.index("height_bias"), layout.index("baro_scale")

    def evaluate(self, x, u):
        return np.array([(1.0 + x[self.js]) * x[2] + x[self.ib]])

    def covariance(self):
        return np.array([[0.05**2]])

    def jacobian(self, x, u, layout):
        h = np.zeros((1, layout.n_err))
        h[0, S.EP.start + 2] = 1.0 + x[self.js]
        h[0, self.es] = x[2]
        h[0, self.eb] = 1.0
        return h


def test_a_new_block_is_one_declaration_plus_its_jacobian_columns():
    blocks = B.BLOCKS + (BARO_SCALE,)
    opts = EskfOptions(height={"bias": "estimate", "bias_random_walk": 0.03, "bias_prior_sd": 0.5},
                       anchor_bias={"mode": "estimate"})
    L = StateLayout(counts=block_counts(opts, 3, 0, 1, blocks), blocks=blocks)
    assert L.count["baro_scale"] == 1 and L.err("baro_scale") == slice(L.n_err - 1, L.n_err)
    # process noise from the declaration, applied by the unchanged kernels
    pn = L.process_noise(np.zeros(4), block_process_noise(opts, L))
    P = np.eye(L.n_err)
    MK.cov_step_blocks(P, _rand_state(np.random.default_rng(0), L), np.zeros(6), 0.5, pn)
    assert P[-1, -1] == pytest.approx(1.0 + 0.03**2 * 0.5, rel=1e-14)
    # its Jacobian columns, pinned by the finite-difference harness
    rng = np.random.default_rng(5)
    for _ in range(3):
        x = _rand_state(rng, L)
        m = ScaledHeight(L)
        np.testing.assert_allclose(m.jacobian(x, np.zeros(6), L), fd_jacobian(m, x, np.zeros(6), L),
                                   rtol=1e-6, atol=1e-8)
    # and its calibration output without further code
    cal = block_calibration(L, x, np.full(L.n_err, 0.2), opts, ["a", "b", "c"])
    assert (cal["baro_scale"], cal["baro_scale_sd"]) == (x[L.nom("baro_scale")][0], 0.2)
    assert list(cal)[-2:] == ["baro_scale", "baro_scale_sd"]


def test_height_bias_is_one_declaration_and_its_jacobian_column():
    """The altimeter bias needs nothing but its declaration and HeightModel's column: the estimator's
    settings, process noise, priors and outputs never name it."""
    import uwbimu.estimation.eskf as eskf_mod
    import uwbimu.estimation.outputs as out_mod
    import uwbimu.estimation.problem as problem_mod

    for mod in (problem_mod, eskf_mod, out_mod, K, MK):
        assert "height" not in inspect.getsource(mod), mod.__name__
    L = StateLayout(n_anchor_bias=2, n_height_bias=1)
    m = HeightModel(0.1, L)
    rng = np.random.default_rng(9)
    x = _rand_state(rng, L)
    np.testing.assert_allclose(m.jacobian(x, np.zeros(6), L), fd_jacobian(m, x, np.zeros(6), L), atol=1e-8)


def test_block_prior_covariance_sets_every_declared_extra_block():
    from uwbimu.estimation.problem import block_prior_covariance

    opts = EskfOptions(anchor_bias={"mode": "estimate", "prior_sd": 0.3}, height={"bias": "estimate"},
                       tdoa_pair_bias={"mode": "estimate", "prior_sd": 0.05})
    noise = ImuNoise(accel_noise_density=0.01, gyro_noise_density=1e-3, accel_bias_rw=1e-4, gyro_bias_rw=1e-5)
    prob, pr = make_settings(opts, list("abc"), np.arange(9.0).reshape(3, 3), noise, 0.1, None, [0, 0, 0],
                             None, [(0, 1)])
    L = prob.layout
    P = np.zeros((L.n_err, L.n_err))
    block_prior_covariance(P, L, pr)
    assert np.array_equal(np.diag(P)[L.err("anchor_bias")], np.full(3, 0.3**2))
    assert np.diag(P)[L.err("pair_bias")].tolist() == [0.05**2]
    assert np.diag(P)[L.err("height_bias")].tolist() == [opts.height.bias_prior_sd**2]
    assert not P[:19].any()  # the base blocks are the initialiser's
