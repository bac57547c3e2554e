"""Analytic Jacobians of the model against numerical derivatives (both airframes)."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import STANDARD_GRAVITY_MPS2, Model, build_model
from gcs_estimator.model.channels import Channel

# Central differences with step 1e-6 relative: truncation ~1e-12, rounding ~1e-10 of the
# function's scale. Entries are compared relative to the Jacobian's largest entry per row.
JACOBIAN_RTOL = 1e-6


def numerical_jacobian(
    f: Callable[[FloatArray], tuple[FloatArray, FloatArray]], x: FloatArray
) -> FloatArray:
    f0 = f(x)[0]
    J = np.zeros((f0.size, x.size))
    for j in range(x.size):
        h = 1e-6 * max(1.0, abs(x[j]))
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        J[:, j] = (f(xp)[0] - f(xm)[0]) / (2 * h)
    return J


def assert_jacobian_close(analytic: FloatArray, numeric: FloatArray) -> None:
    assert np.all(np.isfinite(analytic)), "Jacobian has NaN or inf"
    scale = np.maximum(np.max(np.abs(numeric), axis=1, keepdims=True), 1e-6)
    err = np.abs(analytic - numeric) / scale
    assert float(err.max()) < JACOBIAN_RTOL, f"worst relative error {err.max():.2e}"


@st.composite
def states(draw: st.DrawFn, model: Model, banked: bool = False) -> tuple[FloatArray, FloatArray]:
    """Random augmented states and inputs, alpha up to 1 mrad from +-90 deg (near-singular
    trigonometry) and airspeed down to 30 % of trim (large 1/V terms); banked: with a
    bank angle up to 80 deg and roll and yaw rates as inputs."""
    V0 = float(model.k[eq.V0])
    V = draw(st.floats(0.3 * V0, 2.0 * V0))
    alpha = draw(st.floats(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3))
    theta = draw(st.floats(-1.5, 1.5))
    q = draw(st.floats(-3.0, 3.0))
    beta = np.array([draw(st.floats(-100.0, 100.0)) for _ in range(model.n_coefficients)])
    de = draw(st.floats(-0.5, 0.5))
    propeller = model.k[eq.PROP_KIND] == eq.PROP_PROPELLER
    power = draw(st.floats(0.0, 1.0)) if propeller else draw(st.floats(0.0, 5e4))
    x = model.augment(np.array([V, alpha, theta, q]), beta)
    x[model.biases] = [draw(st.floats(-0.1, 0.1)) for _ in model.bias_names]
    if not banked:
        return x, np.array([de, power])
    phi = draw(st.floats(-1.4, 1.4))
    p, r = draw(st.floats(-2.0, 2.0)), draw(st.floats(-2.0, 2.0))
    return x, np.array([de, power, 1.1, phi, p, r])


PLACED = [
    "sensors.vane_x_m=1.2",
    "sensors.vane_z_m=-0.15",
    "sensors.accel_x_m=-0.3",
    "sensors.accel_z_m=0.08",
    'sensors.bias_states=["alpha", "q", "a_x", "a_z"]',
]
"""The NOC UAV with its sensors away from the CG and four estimated biases."""
ALPHA_RATE = [
    'coefficients.CL=["1", "alpha", "qhat", "elevator", "adhat"]',
    'coefficients.Cm=["1", "alpha", "qhat", "elevator", "adhat"]',
    "truth.CLadot=0",
    "truth.Cmadot=0",
]
"""The NOC UAV with alpha-rate terms in lift and moment (JSBSim's CLadot, Cmadot)."""
GUSTS = ['filter.turbulence.model="states"', "sensors.vane_x_m=0.8", "sensors.accel_z_m=0.05"]
"""The NOC UAV with gust states in the filters' augmented state (and sensors off the CG)."""
PITCH_GUST = [*GUSTS, "airframe.wing_span_m=2.6"]
"""The same with a wing span: the pitch gust's state after the gusts."""
WHITE_PITCH_GUST = [*PLACED, "airframe.wing_span_m=2.6"]
"""White gust noise with a wing span: the pitch gust's state alone after the flight states
(and the sensors off the CG, with biases)."""
INERTIA = [
    "airframe.inertia_xx_kgm2=1.9",
    "airframe.inertia_zz_kgm2=3.1",
    "airframe.inertia_xz_kgm2=0.2",
]
"""Roll and yaw inertia: q-dot's inertial coupling in turns."""
BANKED = {
    "banked": INERTIA,
    "banked placed": [*PLACED, *INERTIA],
    "banked alpha rate": ALPHA_RATE,
    "banked pitch gust": [*PITCH_GUST, *INERTIA],
    "banked white pitch gust": WHITE_PITCH_GUST,
}
"""Turns: the bank angle, roll and yaw rates as inputs (docs/model.md, "Turns")."""


@functools.cache
def _variant(which: str) -> AircraftConfig:
    """The NOC UAV with a variant's overrides, read once for all of a property's examples
    (reading it again for each took a quarter of the test's time; decision 0066)."""
    overrides = {
        "placed": PLACED,
        "alpha rate": ALPHA_RATE,
        "gusts": GUSTS,
        "pitch gust": PITCH_GUST,
        "white pitch gust": WHITE_PITCH_GUST,
        **BANKED,
    }[which]
    return load_config("noc_uav", overrides)


@pytest.mark.parametrize(
    "which",
    ["noc", "hfb", "placed", "alpha rate", "gusts", "pitch gust", "white pitch gust", *BANKED],
)
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_jacobians_match_numerical(
    which: str, data: st.DataObject, noc_config: AircraftConfig, hfb_config: AircraftConfig
) -> None:
    config = {"noc": noc_config, "hfb": hfb_config}.get(which) or _variant(which)
    model = build_model(config)
    x, u = data.draw(states(model, banked=which in BANKED))
    which = which.removeprefix("banked ")
    if which in ("gusts", "pitch gust"):
        x[model.gusts] = [data.draw(st.floats(-5.0, 5.0)) for _ in range(2)] + (
            [data.draw(st.floats(-0.5, 0.5))] if which == "pitch gust" else []
        )
    if which == "white pitch gust":
        x[model.gusts] = data.draw(st.floats(-3.0, 3.0))
    if which == "alpha rate":  # CLadot within what keeps alphadot's denominator away from 0
        x[model.coefficients.start + model.names.index("CLadot")] = data.draw(st.floats(-5, 5))
    _, F = model.f(x, u)
    assert_jacobian_close(F, numerical_jacobian(lambda z: model.f(z, u), x))
    _, H = model.h(x, u)
    assert_jacobian_close(H, numerical_jacobian(lambda z: model.h(z, u), x))


def test_alpha_rate_terms_take_the_models_own_alphadot(noc_config: AircraftConfig) -> None:
    """Cmadot adds Cmadot * alphadot * cbar / (2 V0), alphadot being the model's own f[1];
    with CLadot too, alphadot solves its equation with the lift term included."""
    model = build_model(load_config("noc_uav", ALPHA_RATE))
    names = model.names
    truth = dict(zip(noc_config.coefficient_names, noc_config.truth or (), strict=True))
    beta = np.array([truth.get(n, 0.0) for n in names])
    x = model.augment(np.array([24.0, 0.08, 0.02, 0.3]), beta)
    u = np.array([-0.02, 0.4])
    kc = noc_config.airframe.mean_chord_m / (2 * noc_config.airframe.trim_airspeed_mps)
    f, _ = model.f(x, u)
    h, _ = model.h(x, u)
    i_m = model.coefficients.start + names.index("Cmadot")
    i_l = model.coefficients.start + names.index("CLadot")
    x2 = x.copy()
    x2[i_m] = -6.0
    f2, _ = model.f(x2, u)
    h2, _ = model.h(x2, u)
    mcoef = h2[4] - h[4]  # qdot from the added moment alone
    qbar_term = 0.5 * 1.225 * 24.0**2  # NOC flies at the airframe's constant density
    k = model.k
    scale = qbar_term * k[eq.AREA] * k[eq.CHORD] / k[eq.IYY]
    rho = float(k[eq.RHO])
    scale *= rho / 1.225
    assert mcoef == pytest.approx(scale * -6.0 * f[1] * kc, rel=1e-12)
    assert f2[3] - f[3] == pytest.approx(mcoef, rel=1e-12)
    # With CLadot, alphadot = f[1] satisfies its own equation: the lift term uses it.
    x3 = x2.copy()
    x3[i_l] = 2.0
    f3, _ = model.f(x3, u)
    lift = -0.5 * rho * 24.0 * k[eq.AREA] / k[eq.MASS] * 2.0 * kc * f3[1]
    assert f3[1] - f2[1] == pytest.approx(lift, rel=1e-9)


def test_gust_states_are_what_the_air_data_see_and_decay_as_dryden(
    noc_config: AircraftConfig,
) -> None:
    """With gust states the pitot and vane read V + u_g and alpha + w_g / V, the
    aerodynamics act at that air-relative state, and each gust decays with time constant
    L / V."""
    model = build_model(load_config("noc_uav", ['filter.turbulence.model="states"']))
    still = build_model(noc_config)
    assert still.gusts == slice(0, 0)
    assert model.n == still.n + 2 and model.gusts == slice(4, 6)
    beta = np.array(noc_config.truth)
    x = model.augment(np.array([24.0, 0.05, 0.05, 0.1]), beta)
    x[model.gusts] = [0.8, -1.2]
    u = np.array([0.01, 0.35])
    air = still.augment(np.array([24.8, 0.05 - 1.2 / 24.0, 0.05, 0.1]), beta)
    h = model.h(x, u)[0]
    np.testing.assert_allclose(h[:7], still.h(air, u)[0][:7], rtol=1e-12)
    # The climb rate is the motion over the ground's: V sin(theta - alpha), here level.
    assert h[7] == pytest.approx(24.0 * math.sin(0.05 - 0.05), abs=1e-12)
    f, _ = model.f(x, u)
    np.testing.assert_allclose(f[:4], still.f(air, u)[0][:4], rtol=1e-12)
    t = noc_config.filter.turbulence
    assert f[4] == pytest.approx(-24.0 / t.length_u_m * 0.8)
    assert f[5] == pytest.approx(-24.0 / t.length_w_m * -1.2)


def test_pitch_gust_is_what_the_aerodynamics_take_from_q(noc_config: AircraftConfig) -> None:
    """With a wing span b the gust states end with p_g, the pitch gust being
    q_g = p_g + c w_g (c = pi / (4 b)): the aerodynamics see q - q_g, the gyro and the
    kinematics the body's q, and p_g' = -c V q_g (MIL-F-8785C's lag of w_g' / V)."""
    span = 2.6
    model = build_model(load_config("noc_uav", [*GUSTS[:1], f"airframe.wing_span_m={span}"]))
    gusts = build_model(load_config("noc_uav", GUSTS[:1]))
    assert model.layout.block("gusts").names == ("u_g", "w_g", "p_g")
    c = math.pi / (4.0 * span)
    beta = np.array(noc_config.truth)
    x = model.augment(np.array([24.0, 0.05, 0.05, 0.1]), beta)
    x[model.gusts] = [0.8, -1.2, 0.03]
    qg = 0.03 + c * -1.2
    u = np.array([0.01, 0.35])
    # The same aircraft without the pitch gust, at the aerodynamic pitch rate.
    aero = gusts.augment(np.array([24.0, 0.05, 0.05, 0.1 - qg]), beta)
    aero[gusts.gusts] = [0.8, -1.2]
    f, _ = model.f(x, u)
    fa, _ = gusts.f(aero, u)
    assert f[3] == pytest.approx(fa[3], rel=1e-12)  # the moment: q - q_g
    assert f[2] == pytest.approx(0.1)  # theta' = q
    assert f[1] == pytest.approx(fa[1] + qg, rel=1e-12)  # alpha' = q + ...: the body's q
    assert f[6] == pytest.approx(-c * 24.0 * qg)
    h, _ = model.h(x, u)
    ha, _ = gusts.h(aero, u)
    assert h[3] == pytest.approx(0.1)  # the gyro
    np.testing.assert_allclose(h[4:], ha[4:], rtol=1e-12)  # qdot, a_x, a_z


def test_white_pitch_gust_rides_on_alpha(noc_config: AircraftConfig) -> None:
    """With white gust noise and a wing span the state holds p_g alone, the pitch gust
    being q_g = p_g + c V alpha: the aerodynamics see q - q_g, and p_g' takes alpha's
    own rate out (white_pitch_gust_rows), so that q_g decays as the lag says."""
    span = 2.6
    model = build_model(load_config("noc_uav", [f"airframe.wing_span_m={span}"]))
    still = build_model(noc_config)
    assert model.layout.block("gusts").names == ("p_g",) and model.n == still.n + 1
    c = math.pi / (4.0 * span)
    beta = np.array(noc_config.truth)
    x = model.augment(np.array([24.0, 0.05, 0.05, 0.1]), beta)
    x[4] = 0.02 - c * 24.0 * 0.05  # q_g = 0.02
    u = np.array([0.01, 0.35])
    f, _ = model.f(x, u)
    fa, _ = still.f(still.augment(np.array([24.0, 0.05, 0.05, 0.1 - 0.02]), beta), u)
    assert f[3] == pytest.approx(fa[3], rel=1e-12)
    assert f[1] == pytest.approx(fa[1] + 0.02, rel=1e-12)  # alpha' = q + ...
    # d(q_g)/dt = p_g' + c (V' alpha + V alpha') = -c V q_g
    qg_rate = f[4] + c * (f[0] * 0.05 + 24.0 * f[1])
    assert qg_rate == pytest.approx(-c * 24.0 * 0.02, rel=1e-9)


def test_the_still_air_model_has_no_pitch_gust_state() -> None:
    """The simulators and output error fly build_model(gust_states=False): no gust states
    and no pitch gust's state, whatever the span and the filters' turbulence model (a
    p_g left at 0 there would turn their aerodynamics by c V alpha)."""
    for kind in ("noise", "states"):
        config = load_config(
            "noc_uav", ["airframe.wing_span_m=2.6", f'filter.turbulence.model="{kind}"']
        )
        model = build_model(config, gust_states=False)
        assert model.gusts == slice(0, 0) and not eq.has_pitch_gust(model.arrays)
    no_span = load_config("noc_uav", ["airframe.wing_span_m=0"])
    assert build_model(no_span).gusts == slice(0, 0)


def test_coefficients_have_no_dynamics(noc_config: AircraftConfig) -> None:
    model = build_model(noc_config)
    x = model.augment(np.array([24.0, 0.05, 0.05, 0.1]), np.array(noc_config.truth))
    f, F = model.f(x, np.array([0.0, 0.3]))
    assert np.all(f[4:] == 0.0)
    assert np.all(F[4:] == 0.0)


def test_level_flight_specific_force_is_minus_g(noc_config: AircraftConfig) -> None:
    """At trim the accelerometer reads about (0, -g) in body axes (a_z close to -g)."""
    from gcs_estimator.model.aircraft import trim

    model = build_model(noc_config)
    beta = np.array(noc_config.truth)
    t = trim(model, beta)
    h, _ = model.h(model.augment(t.state, beta), t.inputs)
    g = STANDARD_GRAVITY_MPS2
    alpha = t.state[1]
    # Body-axis gravity reaction in level flight: (g sin(theta), -g cos(theta)), theta = alpha.
    assert h[5] == pytest.approx(g * math.sin(alpha), abs=1e-9)
    assert h[6] == pytest.approx(-g * math.cos(alpha), abs=1e-9)


def test_a_vane_ahead_of_the_cg_reads_the_local_flow(noc_config: AircraftConfig) -> None:
    """Pitching nose-up moves a vane ahead of the CG upward: it reads alpha - q x / V to
    first order (Klein and Morelli, eq. 4.14), and the accelerometers there see the
    rotation's tangential and centripetal terms."""
    model = build_model(load_config("noc_uav", PLACED[:4]))
    at_cg = build_model(noc_config)
    x = model.augment(np.array([24.0, 0.06, 0.06, 0.2]), np.array(noc_config.truth))
    u = np.array([0.0, 0.4])
    h, _ = model.h(x, u)
    h0, _ = at_cg.h(x, u)
    V, alpha, q = 24.0, 0.06, 0.2
    assert h[1] == pytest.approx(alpha - q * 1.2 / V, abs=2e-4)
    assert h[5] == pytest.approx(h0[5] + h0[4] * 0.08 + q * q * 0.3, rel=1e-12)
    assert h[6] == pytest.approx(h0[6] + h0[4] * 0.3 - q * q * 0.08, rel=1e-12)
    np.testing.assert_array_equal(h[[0, 2, 3, 4]], h0[[0, 2, 3, 4]])


@pytest.mark.parametrize("wind", [(-8.0, 0.0), (5.0, 2.0), (0.0, -3.0)])
def test_a_trimmed_aircraft_in_a_steady_wind_stays_trimmed(
    wind: tuple[float, float], noc_config: AircraftConfig
) -> None:
    """A uniform wind (horizontal, vertical [m/s]) carries the aircraft along without
    changing its motion through the air: flown over the ground (wind_slope), the
    trimmed state does not change."""
    from gcs_estimator.model.aircraft import trim

    model = build_model(noc_config)
    beta = np.array(noc_config.truth)
    t = trim(model, beta)
    Va, alpha_a, theta = t.state[0], t.state[1], t.state[2]
    gamma_a = theta - alpha_a
    vx, vz = Va * math.cos(gamma_a) + wind[0], Va * math.sin(gamma_a) + wind[1]
    V, alpha = math.hypot(vx, vz), theta - math.atan2(vz, vx)
    gust = np.array([Va - V, (alpha_a - alpha) * V])
    x = model.augment(np.array([V, alpha, theta, 0.0]), beta)
    np.testing.assert_allclose(eq.air_relative(x, gust)[:4], t.state, atol=1e-12)
    f = eq.wind_slope(x, t.inputs, gust, model.arrays)
    assert np.max(np.abs(f[:4])) < 1e-9, f[:4]


def test_forces_act_on_the_ground_path_in_a_gust(noc_config: AircraftConfig) -> None:
    """Pulling up through a vertical gust: the lift and drag, which act across and along
    the air-relative velocity, turn by the gust angle delta onto the ground velocity.
    Vdot and alphadot over the ground are the force's projections on the ground path
    (checked here against that projection computed in Earth axes)."""
    model = build_model(noc_config)
    beta = np.array(noc_config.truth)
    x = model.augment(np.array([24.0, 0.05, 0.08, 0.2]), beta)
    u = np.array([-0.03, 0.4])
    gust = np.array([0.7, -1.2])
    xa = eq.air_relative(x, gust)
    f_air, _ = model.f(xa, u)  # still-air equations at the air state: forces on the air path
    f = eq.wind_slope(x, u, gust, model.arrays)
    # The force per mass in body axes, from the still-air slope at the air state.
    Va, aa = xa[0], xa[1]
    ax_air = f_air[0] * math.cos(aa) - Va * (f_air[1] - x[3]) * math.sin(aa)
    az_air = f_air[0] * math.sin(aa) + Va * (f_air[1] - x[3]) * math.cos(aa)
    # Gravity is in them too (projected on the air path and back): body-axis components
    # are the same force whichever path it is then projected on.
    V, a = x[0], x[1]
    assert f[0] == pytest.approx(ax_air * math.cos(a) + az_air * math.sin(a), rel=1e-9)
    assert f[1] - x[3] == pytest.approx((az_air * math.cos(a) - ax_air * math.sin(a)) / V, rel=1e-9)


def test_a_clock_reset_takes_the_white_pitch_gust_afresh_with_alpha() -> None:
    """core.rebase takes the flight states afresh from the measurement; the pitch gust's
    state of white gust noise rides on alpha (q_g = p_g + c V alpha), so it is taken
    afresh with them: q_g = 0 and p_g tied to alpha's belief, the coefficients kept."""
    from gcs_estimator.estimation.filters import core

    config = load_config("noc_uav", ["airframe.wing_span_m=2.6"])
    model = build_model(config)
    tuning = core.tuning_of(config, model, "EKF")
    u = np.array([0.01, 0.35])
    y = np.array([24.0, 0.05, 0.04, 0.0, 0.0, 0.0, -9.8])
    state = core.initial_state(model, tuning, 0.0, u, y)
    x = state.x.copy()
    x[model.coefficients] = 1.0
    x[4] = 0.3  # some pitch gust state before the reset
    old = state._replace(x=x)
    y2 = y.copy()
    y2[0], y2[1] = 26.0, 0.08
    new = core.rebase(old, model, tuning, 100.0, y2)
    c = math.pi / (4.0 * 2.6)
    assert new.x[4] + c * new.x[0] * new.x[1] == pytest.approx(0.0, abs=1e-12)
    assert new.P[4, 1] == pytest.approx(-c * new.x[0] * new.P[1, 1])
    assert new.P[4, 0] == pytest.approx(-c * new.x[1] * new.P[0, 0])
    np.testing.assert_array_equal(new.x[model.coefficients], 1.0)


def test_afresh_the_states_a_frame_does_not_measure_start_where_they_were() -> None:
    """core.rebase at a frame that measures only some flight states (a link's pitch rate
    between its slower airspeed and attitude samples): those it measures start from the
    measurement, the others from the belief before (not trim speed and zeros), every
    flight state with its initial sigma and uncorrelated; without a vane, alpha from the
    frame's climb rate where it has one."""
    from gcs_estimator.estimation.filters import core

    config = load_config("noc_uav", ["simulation.vane=false"])
    model = build_model(config)
    tuning = core.tuning_of(config, model, "EKF")
    u = np.array([0.01, 0.35])
    nan = math.nan
    y = np.array([19.0, nan, 0.2, 0.1, nan, nan, nan, nan])
    before = core.initial_state(model, tuning, 0.0, u, y)
    x = before.x.copy()
    x[:4] = [19.0, 0.07, 0.2, 0.1]
    x[model.coefficients] = 1.0
    old = before._replace(x=x, P=before.P * 0.01)
    only_q = np.array([nan, nan, nan, 0.05, nan, nan, nan, nan])
    new = core.rebase(old, model, tuning, 1.0, only_q)
    np.testing.assert_array_equal(new.x[:4], [19.0, 0.07, 0.2, 0.05])
    fresh = core.initial_state(model, tuning, 1.0, u, only_q)
    np.testing.assert_array_equal(new.P[:4, :4], fresh.P[:4, :4])
    np.testing.assert_array_equal(new.x[model.coefficients], 1.0)
    climbing = only_q.copy()
    climbing[Channel.HDOT] = 2.0
    new = core.rebase(old, model, tuning, 1.0, climbing)
    assert new.x[1] == pytest.approx(eq.alpha_from_climb(19.0, 0.2, 2.0, 0.0))
    first = core.initial_state(model, tuning, 1.0, u, only_q)  # a pass's first frame
    assert first.x[0] == model.k[eq.V0] and first.x[2] == 0.0  # no belief before it


def _wings_level_rows(x: FloatArray, u: FloatArray, model: Model) -> FloatArray:
    """The paper's wings-level equations (docs/model.md before "Turns"), written out."""
    k = model.k
    V, alpha, theta, q = x[:4]
    rho = float(u[2])
    Fe, dFe = eq.thrust(V, u[1], rho, k)
    C, _ = eq.coefficients(x, u, model.arrays, rho, Fe, dFe)
    qbar = 0.5 * rho * V * V
    m, g = k[eq.MASS], k[eq.GRAV]
    return np.array(
        [
            -qbar * k[eq.AREA] / m * C[0]
            + g * math.sin(alpha - theta)
            + Fe / m * math.cos(alpha + k[eq.SIGMA_T]),
            -qbar * k[eq.AREA] / (m * V) * C[1]
            + q
            + g / V * math.cos(alpha - theta)
            - Fe / (m * V) * math.sin(alpha + k[eq.SIGMA_T]),
            q,
            qbar * k[eq.AREA] * k[eq.CHORD] / k[eq.IYY] * C[2] + Fe * k[eq.ARM] / k[eq.IYY],
        ]
    )


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_wings_level_is_the_papers_model(data: st.DataObject) -> None:
    """phi = p = r = 0 (or absent, or NaN) gives the wings-level equations: the turn's terms
    vanish bit for bit, inertias or not."""
    model = build_model(load_config("noc_uav", [*INERTIA, *PLACED]))
    x, u = data.draw(states(model))
    level = model.inputs(np.array([*u, 1.1, 0.0, 0.0, 0.0]))
    f, F = model.f(x, level)
    np.testing.assert_allclose(f[:4], _wings_level_rows(x, level, model), rtol=1e-12, atol=1e-12)
    for other in (np.array([*u, 1.1]), np.array([*u, 1.1, math.nan, math.nan, math.nan])):
        f2, F2 = model.f(x, model.inputs(other))
        assert np.array_equal(f2, f) and np.array_equal(F2, F)
        h2, H2 = model.h(x, model.inputs(other))
        h, H = model.h(x, level)
        assert np.array_equal(h2, h) and np.array_equal(H2, H)


def test_a_level_turn_holds_its_pitch(noc_config: AircraftConfig) -> None:
    """In a level coordinated turn at bank phi the heading turns at Omega = g tan(phi)/V,
    which the body feels as q = Omega sin(phi), r = Omega cos(phi): theta stays put
    (thetadot = q cos(phi) - r sin(phi) = 0) though the pitch gyro reads q > 0."""
    model = build_model(noc_config)
    V, phi = 20.0, math.radians(30.0)
    omega = STANDARD_GRAVITY_MPS2 * math.tan(phi) / V
    q, r = omega * math.sin(phi), omega * math.cos(phi)
    x = model.augment(np.array([V, 0.08, 0.08, q]), np.zeros(model.n_coefficients))
    f, _ = model.f(x, model.inputs([0.0, 0.5, 1.2, phi, 0.0, r]))
    assert q > 0.05
    assert abs(f[2]) < 1e-15
