"""Longitudinal aircraft model: dynamics, observations and their analytic Jacobians.

Source: Meng, Liu and Veres (2010), eq. 11-14, as corrected in docs/model.md.

Augmented state x_a (model.state): the flight states [V, alpha, theta, q] first
(airspeed [m/s], angle of attack [rad], pitch angle [rad], pitch rate [rad/s]), the
aerodynamic coefficients from ``coef_start`` on, and whatever other blocks the layout
declares. Input u = [de, throttle_or_thrust, rho, phi, p, r]: elevator [rad] (positive
trailing edge down), throttle [0..1] for the propeller model or thrust [N] when thrust is
measured, the air density [kg/m^3] at the sample, and the lateral motion as measured
inputs (docs/model.md, "Turns"): bank angle phi [rad], roll rate p and yaw rate r
[rad/s], sideslip taken as zero. A two-element u flies at the airframe's constant density
k[RHO], a u without the last three (or with them NaN) wings level.

The functions take the aircraft as ModelArrays: the airframe packed into a float array
``k`` (indices below), the coefficient structure as two int arrays, ``axis[i]`` (0 = CD,
1 = CL, 2 = Cm) and ``regressor[i]`` (0 = 1, 1 = alpha, 2 = qhat, 3 = elevator,
4 = V/V0, 5 = adhat) of coefficient i, and the layout offsets. They are written with scalar
arithmetic and loops only, so that the very same source runs as plain Python (the
reference path, which imports no compiler) and compiles with numba (model.compiled).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.model.channels import N_FLIGHT, N_OBS

# Packed airframe constants (see pack_constants in model.aircraft).
MASS, AREA, CHORD, IYY, RHO, GRAV, V0, SIGMA_T, ARM = 0, 1, 2, 3, 4, 5, 6, 7, 8
PROP_KIND, PROP_AREA, PROP_COEF, MOTOR_K = 9, 10, 11, 12
VANE_X, VANE_Z, ACCEL_X, ACCEL_Z = 13, 14, 15, 16
GUST_LU, GUST_LW = 17, 18
"""Scale lengths [m] of the filters' gust states (where the layout has them)."""
SPAN = 19
"""Wing span [m]: the scale of the pitch gust (0: none)."""
IXX, IZZ, IXZ = 20, 21, 22
"""Roll and yaw inertia and their product [kg m^2] for q-dot's inertial coupling in turns
(Ixx = Izz = 0: the coupling left out)."""
N_CONST = 23
PROP_MEASURED, PROP_PROPELLER, PROP_ENGINE = 0.0, 1.0, 2.0
"""Thrust measured; a propeller whose speed the throttle sets (an electric motor: the
paper's model); a propeller whose shaft power the throttle sets (a piston engine or a
turboprop)."""

N_STATE = N_FLIGHT
"""The flight states [V, alpha, theta, q] are x_a[0:4]."""
AXIS_D, AXIS_L, AXIS_M = 0, 1, 2
REG_ONE, REG_ALPHA, REG_QHAT, REG_ELEV, REG_SPEED, REG_ADOT = 0, 1, 2, 3, 4, 5


class ModelArrays(NamedTuple):
    """One aircraft as the equations and the compiled kernels take it."""

    k: FloatArray
    """Airframe and propulsion constants, indexed MASS .. MOTOR_K."""
    axis: IntArray
    """Axis (AXIS_D, AXIS_L, AXIS_M) of each coefficient."""
    regressor: IntArray
    """Regressor (REG_ONE .. REG_SPEED) of each coefficient."""
    coef_start: int
    """Index of the first coefficient in the augmented state."""
    n_dynamic: int
    """Leading elements of the augmented state with dynamics; F is zero below them."""
    bias_channel: IntArray
    """Observation channel of each estimated sensor bias."""
    bias_start: int
    """Index of the first sensor bias in the augmented state."""


def density(u: FloatArray, k: FloatArray) -> float:
    """Air density [kg/m^3]: the input's third element where given, else the airframe's."""
    if u.shape[0] > 2:
        return float(u[2])
    return float(k[RHO])


def bank(u: FloatArray) -> tuple[float, float, float]:
    """(phi, p, r) of the inputs: bank angle [rad], roll and yaw rate [rad/s]; zero (wings
    level) where u has none or they are not numbers."""
    if u.shape[0] < 6:
        return 0.0, 0.0, 0.0
    phi = float(u[3]) if math.isfinite(u[3]) else 0.0
    p = float(u[4]) if math.isfinite(u[4]) else 0.0
    r = float(u[5]) if math.isfinite(u[5]) else 0.0
    return phi, p, r


def inertial_coupling(u: FloatArray, k: FloatArray) -> float:
    """q-dot's inertial coupling in a turn [rad/s^2]: ((Izz - Ixx) p r + Ixz (r^2 - p^2))/Iy
    (Euler's pitch equation); 0 without Ixx and Izz."""
    if k[IXX] <= 0.0 or k[IZZ] <= 0.0:
        return 0.0
    _, p, r = bank(u)
    return float(((k[IZZ] - k[IXX]) * p * r + k[IXZ] * (r * r - p * p)) / k[IYY])


def thrust(V: float, u1: float, rho: float, k: FloatArray) -> tuple[float, float]:
    """Thrust Fe [N] and dFe/dV [N s/m] at air density rho [kg/m^3].

    Propeller model (docs/model.md): Fe = 0.5*rho*S_prop*C_prop*((k_motor*throttle)^2 - V^2).
    Engine model (a piston engine or turboprop, model.propeller): the throttle sets the
    thrust power, Fe = throttle * P_thrust / sqrt(V^2 + V_s^2), P_thrust = PROP_COEF [W]
    and V_s = MOTOR_K [m/s] (the static thrust is P_thrust / V_s).
    Measured thrust: Fe = u1.
    """
    if k[PROP_KIND] == PROP_PROPELLER:
        c = 0.5 * rho * k[PROP_AREA] * k[PROP_COEF]
        vm = k[MOTOR_K] * u1
        return c * (vm * vm - V * V), -2.0 * c * V
    if k[PROP_KIND] == PROP_ENGINE:
        vs = k[MOTOR_K]
        r2 = V * V + vs * vs
        r = math.sqrt(r2)
        f = u1 * k[PROP_COEF] / r
        return f, -f * V / r2
    return u1, 0.0


def throttle_driven(k: FloatArray) -> bool:
    """Whether the second input is a throttle (a propeller or engine model), not thrust."""
    return bool(k[PROP_KIND] != PROP_MEASURED)


def aero_coefficients(
    x: FloatArray, u: FloatArray, m: ModelArrays
) -> tuple[FloatArray, FloatArray]:
    """Coefficients C = [CD, CL, Cm] and their Jacobian dC/dx_a (3 x n), without the
    alpha-rate terms (coefficients() adds them).

    C_axis = sum_i beta_i * r_regressor(i) with
    r = [1, alpha, q*cbar/(2*V0), de, V/V0, alphadot*cbar/(2*V0)] (paper eq. 12,
    generalised to a configured structure).
    """
    k = m.k
    n = x.shape[0]
    V = x[0]
    alpha = x[1]
    q = x[3]
    pg = pitch_gust_index(m)
    states = has_gust_states(m)
    cg = 0.0
    if pg >= 0:  # the aerodynamic pitch rate: q less the pitch gust (pitch_gust_rows)
        cg = pitch_gust_scale(k)
        q = q - x[pg] - (cg * x[N_FLIGHT + 1] if states else cg * V * alpha)
    qhat_per_q = k[CHORD] / (2.0 * k[V0])
    r = np.empty(6)
    r[REG_ONE] = 1.0
    r[REG_ALPHA] = alpha
    r[REG_QHAT] = q * qhat_per_q
    r[REG_ELEV] = u[0]
    r[REG_SPEED] = V / k[V0]
    r[REG_ADOT] = 0.0
    C = np.zeros(3)
    dC = np.zeros((3, n))
    c0 = m.coef_start
    for i in range(m.axis.shape[0]):
        a = m.axis[i]
        j = m.regressor[i]
        b = x[c0 + i]
        C[a] += b * r[j]
        dC[a, c0 + i] = r[j]
        if j == REG_ALPHA:
            dC[a, 1] += b
        elif j == REG_QHAT:
            dC[a, 3] += b * qhat_per_q
            if pg >= 0:
                dC[a, pg] -= b * qhat_per_q
                if states:
                    dC[a, N_FLIGHT + 1] -= cg * b * qhat_per_q
                else:
                    dC[a, 0] -= cg * alpha * b * qhat_per_q
                    dC[a, 1] -= cg * V * b * qhat_per_q
        elif j == REG_SPEED:
            dC[a, 0] += b / k[V0]
    return C, dC


def _angles(x: FloatArray, u: FloatArray, k: FloatArray) -> FloatArray:
    """Gravity's and thrust's angles (docs/model.md, "Turns"), as [G1, G2, dG1/dtheta,
    dG2/dtheta, sin(alpha + sigma_T), cos(alpha + sigma_T)] with, e = cos(phi) - 1,

        G1 = sin(alpha) cos(phi) cos(theta) - cos(alpha) sin(theta)
           = sin(alpha - theta) + e sin(alpha) cos(theta)       (Vdot's g)
        G2 = cos(alpha) cos(phi) cos(theta) + sin(alpha) sin(theta)
           = cos(alpha - theta) + e cos(alpha) cos(theta)       ((V/g) alphadot's g)

    dG1/dalpha = G2, dG2/dalpha = -G1. Written as the wings-level terms plus e times the
    rest, wings level (e = 0) gives the wings-level equations bit for bit."""
    alpha = x[1]
    theta = x[2]
    phi, _, _ = bank(u)
    e = math.cos(phi) - 1.0
    sa = math.sin(alpha)
    ca = math.cos(alpha)
    st = math.sin(theta)
    ct = math.cos(theta)
    sat = math.sin(alpha - theta)
    cat = math.cos(alpha - theta)
    out = np.empty(6)
    out[0] = sat + e * sa * ct
    out[1] = cat + e * ca * ct
    out[2] = -cat - e * sa * st
    out[3] = sat - e * ca * st
    out[4] = math.sin(alpha + k[SIGMA_T])
    out[5] = math.cos(alpha + k[SIGMA_T])
    return out


def _alpha_rate(
    x: FloatArray,
    m: ModelArrays,
    C: FloatArray,
    dC: FloatArray,
    rho: float,
    Fe: float,
    dFe: float,
    row: FloatArray,
    angles: FloatArray,
) -> float:
    """alphadot given the coefficients C, dC (paper eq. 11) and the angles (_angles), its
    derivative d/dx_a written into row [n]:

        alphadot = -(qbar*S/(m*V))*CL + q + (g/V)*G2 - (Fe/(m*V))*sin(alpha + sigma_T)

    G2 = cos(alpha) cos(phi) cos(theta) + sin(alpha) sin(theta), cos(alpha - theta) wings
    level (docs/model.md, "Turns")."""
    k = m.k
    V = x[0]
    A = k[AREA] / k[MASS]
    g = k[GRAV]
    mass = k[MASS]
    g1 = angles[0]
    g2 = angles[1]
    sas = angles[4]
    cas = angles[5]
    for j in range(row.shape[0]):
        row[j] = -0.5 * rho * V * A * dC[1, j]
    # Explicit dependence on V, alpha, theta, q beyond that through the coefficients.
    row[0] += (
        -0.5 * rho * A * C[1] - g / (V * V) * g2 - (dFe / (mass * V) - Fe / (mass * V * V)) * sas
    )
    row[1] += -g / V * g1 - Fe / (mass * V) * cas
    row[2] += g / V * angles[3]
    row[3] += 1.0
    return float(-0.5 * rho * V * A * C[1] + x[3] + g / V * g2 - Fe / (mass * V) * sas)


def has_alpha_rate(m: ModelArrays) -> bool:
    """Whether some coefficient has the alpha-rate regressor adhat."""
    for i in range(m.regressor.shape[0]):  # noqa: SIM110 (numba compiles loops, not any())
        if m.regressor[i] == REG_ADOT:
            return True
    return False


def coefficients(
    x: FloatArray, u: FloatArray, m: ModelArrays, rho: float, Fe: float, dFe: float
) -> tuple[FloatArray, FloatArray]:
    """C = [CD, CL, Cm] and dC/dx_a [3 x n], alpha-rate terms included.

    The regressor adhat = alphadot*cbar/(2*V0) takes alphadot from the model's own alpha
    equation (JSBSim's CLadot, Cmadot). With CL's own adhat coefficient CLad, alphadot
    appears on both sides of that equation; it is linear there, so

        alphadot = alphadot_0 / (1 + kappa*cbar/(2*V0)*CLad),   kappa = qbar*S/(m*V),

    alphadot_0 being the equation with adhat = 0. Its Jacobian is that of the quotient.
    """
    C, dC = aero_coefficients(x, u, m)
    if not has_alpha_rate(m):
        return C, dC
    k = m.k
    n = x.shape[0]
    V = x[0]
    kc = k[CHORD] / (2.0 * k[V0])
    kappa = 0.5 * rho * V * k[AREA] / k[MASS]
    row0 = np.zeros(n)
    f0 = _alpha_rate(x, m, C, dC, rho, Fe, dFe, row0, _angles(x, u, k))
    c0 = m.coef_start
    cl_ad = 0.0
    for i in range(m.axis.shape[0]):
        if m.regressor[i] == REG_ADOT and m.axis[i] == AXIS_L:
            cl_ad += x[c0 + i]
    den = 1.0 + kappa * kc * cl_ad
    f1 = f0 / den
    adhat = kc * f1
    dden = np.zeros(n)
    dden[0] = 0.5 * rho * k[AREA] / k[MASS] * kc * cl_ad
    for i in range(m.axis.shape[0]):
        if m.regressor[i] == REG_ADOT and m.axis[i] == AXIS_L:
            dden[c0 + i] += kappa * kc
    for i in range(m.axis.shape[0]):
        if m.regressor[i] != REG_ADOT:
            continue
        a = m.axis[i]
        b = x[c0 + i]
        C[a] += b * adhat
        dC[a, c0 + i] = adhat
        for j in range(n):
            dC[a, j] += b * kc * (row0[j] - f1 * dden[j]) / den
    return C, dC


def dynamics(x: FloatArray, u: FloatArray, model: ModelArrays) -> tuple[FloatArray, FloatArray]:
    """State derivative f(x_a, u) and its Jacobian F = df/dx_a [n x n] (dynamics_rows
    with the zero rows below n_dynamic)."""
    f, F_rows = dynamics_rows(x, u, model)
    n = x.shape[0]
    F = np.zeros((n, n))
    for i in range(F_rows.shape[0]):
        for j in range(n):
            F[i, j] = F_rows[i, j]
    return f, F


def has_gust_states(model: ModelArrays) -> bool:
    """Whether the augmented state holds gust states [u_g, w_g] after the flight states
    (the dynamic states: flight states, then [u_g, w_g] or [u_g, w_g, p_g] with gust
    states, or [p_g] alone with white gust noise and a pitch gust)."""
    return model.n_dynamic >= N_FLIGHT + 2


def pitch_gust_index(model: ModelArrays) -> int:
    """Where the pitch gust's state p_g sits (a wing span given), or -1: after the gust
    states, or right after the flight states when turbulence is white process noise."""
    if model.n_dynamic == N_FLIGHT + 3:
        return N_FLIGHT + 2
    if model.n_dynamic == N_FLIGHT + 1:
        return N_FLIGHT
    return -1


def has_pitch_gust(model: ModelArrays) -> bool:
    """Whether the augmented state holds the pitch gust's state p_g."""
    return pitch_gust_index(model) >= 0


def pitch_gust_scale(k: FloatArray) -> float:
    """c = pi / (4 b) [1/m] of the pitch gust (pitch_gust_rows), b the wing span."""
    return math.pi / (4.0 * float(k[SPAN]))


def pitch_gust_rows(x: FloatArray, k: FloatArray, f: FloatArray, F: FloatArray) -> None:
    """The pitch gust's state p_g: its derivative and Jacobian row (in place).

    MIL-F-8785C's pitch gust is q_g = (s / V) / (1 + (4 b / (pi V)) s) w_g: the rate at
    which the vertical gust turns the flow, lagged over the span b, which the tail meets
    after the wing. The aerodynamics see the pitch rate q - q_g (JSBSim's q-aero). With
    c = pi / (4 b), q_g' = c w_g' - c V q_g, so the state p_g = q_g - c w_g follows
    p_g' = -c V q_g = -c V (p_g + c w_g) and takes no noise of its own: Q stays diagonal
    and w_g's noise drives q_g through q_g = p_g + c w_g exactly.
    """
    c = pitch_gust_scale(k)
    p = N_FLIGHT + 2
    w = N_FLIGHT + 1
    V = x[0]
    qg = x[p] + c * x[w]
    f[p] = -c * V * qg
    F[p, 0] = -c * qg
    F[p, p] = -c * V
    F[p, w] = -c * c * V


def white_pitch_gust_rows(x: FloatArray, k: FloatArray, f: FloatArray, F: FloatArray) -> None:
    """The pitch gust's state where turbulence is white process noise on the air-relative
    states (in place; f and F hold the flight states' rows).

    The noise on alpha stands for the gust angle's rate w_g' / V, so the pitch gust is
    q_g' = c V (noise_alpha - q_g) (pitch_gust_rows). The state p_g = q_g - c V alpha
    follows, alpha' being f_alpha + noise_alpha and V' f_V (+ noise, whose product with
    alpha is second order),

        p_g' = -c V q_g - c alpha f_V - c V f_alpha,    q_g = p_g + c V alpha,

    with no noise of its own: Q stays diagonal, and alpha's noise drives q_g."""
    c = pitch_gust_scale(k)
    p = N_FLIGHT
    V = x[0]
    alpha = x[1]
    qg = x[p] + c * V * alpha
    f[p] = -c * V * qg - c * alpha * f[0] - c * V * f[1]
    for j in range(F.shape[1]):
        F[p, j] = -c * alpha * F[0, j] - c * V * F[1, j]
    F[p, p] += -c * V
    F[p, 0] += -c * qg - c * c * V * alpha - c * f[1]
    F[p, 1] += -c * c * V * V - c * f[0]


def _gust_chain(x: FloatArray, J: FloatArray, rows: int) -> None:
    """J (rows x n), the Jacobian of a function of air_relative(x, x[4:6]) with respect
    to the air-relative state, becomes that with respect to x (in place): V_a = V + u_g,
    alpha_a = alpha + w_g / V."""
    V = x[0]
    wg = x[N_FLIGHT + 1]
    for i in range(rows):
        dV = J[i, 0]
        da = J[i, 1]
        J[i, 0] = dV - da * wg / (V * V)
        J[i, N_FLIGHT] += dV
        J[i, N_FLIGHT + 1] += da / V


def dynamics_rows(
    x: FloatArray, u: FloatArray, model: ModelArrays
) -> tuple[FloatArray, FloatArray]:
    """State derivative f(x_a, u) and the rows of F = df/dx_a that are not zero, the
    first n_dynamic (still_rows).

    With gust states [u_g, w_g] (filter.turbulence.model = "states"), the flight states are the
    motion over the ground and the aerodynamics see air_relative(x, [u_g, w_g]); the
    equations of still_rows hold at that air-relative state (first order in the gust
    angle: equations.wind_slope has the exact projection), and each gust is a
    first-order Dryden process, u_g' = -(V/L_u) u_g + noise, w_g' = -(V/L_w) w_g + noise;
    with a wing span, the pitch gust's state follows (pitch_gust_rows).
    """
    if not has_gust_states(model):
        f, F = still_rows(x, u, model)
        if has_pitch_gust(model):
            white_pitch_gust_rows(x, model.k, f, F)
        return f, F
    g0 = N_FLIGHT
    xa = air_relative(x, x[g0 : g0 + 2])
    f, F = still_rows(xa, u, model)
    _gust_chain(x, F, N_FLIGHT)
    k = model.k
    V = x[0]
    f[g0] = -V / k[GUST_LU] * x[g0]
    f[g0 + 1] = -V / k[GUST_LW] * x[g0 + 1]
    F[g0, 0] = -x[g0] / k[GUST_LU]
    F[g0, g0] = -V / k[GUST_LU]
    F[g0 + 1, 0] = -x[g0 + 1] / k[GUST_LW]
    F[g0 + 1, g0 + 1] = -V / k[GUST_LW]
    if has_pitch_gust(model):
        pitch_gust_rows(x, k, f, F)
    return f, F


def still_rows(x: FloatArray, u: FloatArray, model: ModelArrays) -> tuple[FloatArray, FloatArray]:
    """State derivative f(x_a, u) and the rows of F = df/dx_a that are not zero, the
    first n_dynamic, in still air (paper eq. 11, corrected, with the turn's terms of
    docs/model.md, "Turns": bank phi, roll and yaw rate p, r as inputs, no sideslip).

        Vdot     = -(qbar*S/m)*CD + g*G1 + (Fe/m)*cos(alpha + sigma_T)
        alphadot = -(qbar*S/(m*V))*CL + q + (g/V)*G2 - (Fe/(m*V))*sin(alpha + sigma_T)
        thetadot = q*cos(phi) - r*sin(phi)
        qdot     = (qbar*S*cbar/Iy)*Cm + Fe*arm/Iy + ((Izz-Ixx)*p*r + Ixz*(r^2-p^2))/Iy
        betadot  = 0

    G1 = sin(alpha) cos(phi) cos(theta) - cos(alpha) sin(theta) and G2 =
    cos(alpha) cos(phi) cos(theta) + sin(alpha) sin(theta) (_angles): sin(alpha - theta)
    and cos(alpha - theta) wings level, the paper's case.

    Returns f [n] and F[:n_dynamic] [n_dynamic x n], n the dimension of the augmented
    state.
    """
    k = model.k
    n = x.shape[0]
    V = x[0]
    q = x[3]
    m = k[MASS]
    A = k[AREA] / m
    g = k[GRAV]
    rho = density(u, k)
    Fe, dFe = thrust(V, u[1], rho, k)
    C, dC = coefficients(x, u, model, rho, Fe, dFe)
    qbar = 0.5 * rho * V * V
    angles = _angles(x, u, k)
    cas = angles[5]
    sas = angles[4]
    mcoef = k[AREA] * k[CHORD] / k[IYY]
    phi, _, r = bank(u)
    cphi = math.cos(phi)

    f = np.zeros(n)
    F = np.zeros((model.n_dynamic, n))
    f[0] = -qbar * A * C[0] + g * angles[0] + Fe / m * cas
    f[1] = _alpha_rate(x, model, C, dC, rho, Fe, dFe, F[1], angles)
    f[2] = q * cphi - r * math.sin(phi)
    f[3] = qbar * mcoef * C[2] + Fe * k[ARM] / k[IYY] + inertial_coupling(u, k)

    for j in range(n):
        F[0, j] = -qbar * A * dC[0, j]
        F[3, j] = qbar * mcoef * dC[2, j]
    # Explicit dependence on V, alpha, theta, q beyond that through the coefficients.
    F[0, 0] += -rho * V * A * C[0] + dFe / m * cas
    F[0, 1] += g * angles[1] - Fe / m * sas
    F[0, 2] += g * angles[2]
    F[2, 3] = cphi
    F[3, 0] += rho * V * mcoef * C[2] + dFe * k[ARM] / k[IYY]
    return f, F


def climb_rate(x: FloatArray, u: FloatArray) -> tuple[float, float, float, float]:
    """Climb rate h-dot [m/s, up] of the flight states and its derivatives by V, alpha,
    theta (docs/model.md, "Alpha without a vane"): h-dot = V sin(gamma),

        sin(gamma) = cos(alpha) sin(theta) - cos(phi) sin(alpha) cos(theta)

    (sideslip zero; wings level gamma = theta - alpha)."""
    V = x[0]
    sa = math.sin(x[1])
    ca = math.cos(x[1])
    st = math.sin(x[2])
    ct = math.cos(x[2])
    phi, _, _ = bank(u)
    cphi = math.cos(phi)
    sg = ca * st - cphi * sa * ct
    return V * sg, sg, V * (-sa * st - cphi * ca * ct), V * (ca * ct + cphi * sa * st)


def alpha_from_climb(V: float, theta: float, climb: float, phi: float) -> float:
    """The angle of attack [rad] at which climb_rate gives `climb` [m/s]: alpha =
    theta - gamma wings level, gamma = asin(climb / V); in a bank, the root of
    cos(alpha) sin(theta) - cos(phi) sin(alpha) cos(theta) = climb / V nearest it.
    NaN where V is not positive or a value is missing."""
    if not (V > 0.0 and math.isfinite(theta) and math.isfinite(climb)):
        return math.nan
    phi = phi if math.isfinite(phi) else 0.0
    a = math.sin(theta)
    b = math.cos(phi) * math.cos(theta)
    r = math.hypot(a, b)
    s = max(-1.0, min(1.0, climb / V / r))
    return math.acos(s) - math.atan2(b, a)


def observe(x: FloatArray, u: FloatArray, model: ModelArrays) -> tuple[FloatArray, FloatArray]:
    """Observations h(x_a, u) and H = dh/dx_a (still_observe); with gust states, of the
    air-relative state (the pitot, the vane and the aerodynamic forces see the air) but
    for the climb rate, which is the motion over the ground's: the vertical wind is
    what tells the vane's alpha and the climb rate's apart (decision 0049)."""
    if not has_gust_states(model):
        return still_observe(x, u, model)
    xa = air_relative(x, x[N_FLIGHT : N_FLIGHT + 2])
    h, H = still_observe(xa, u, model)
    _gust_chain(x, H, N_OBS)
    c = N_OBS - 1
    ground, dV, da, dt = climb_rate(x, u)
    h[c] += ground - climb_rate(xa, u)[0]
    for j in range(N_FLIGHT + 2):
        H[c, j] = 0.0
    H[c, 0] = dV
    H[c, 1] = da
    H[c, 2] = dt
    return h, H


def still_observe(
    x: FloatArray, u: FloatArray, model: ModelArrays
) -> tuple[FloatArray, FloatArray]:
    """Observations h(x_a, u) and H = dh/dx_a (paper eq. 13-14, C_Z corrected).

        y = [V, alpha, theta, q, qdot, a_x, a_z, h_dot]
        a_x = (qbar*S/m)*C_X + (Fe/m)*cos(sigma_T),  C_X =  CL*sin(alpha) - CD*cos(alpha)
        a_z = (qbar*S/m)*C_Z - (Fe/m)*sin(sigma_T),  C_Z = -CL*cos(alpha) - CD*sin(alpha)

    a_x, a_z are body-axis specific forces [m/s^2]; qdot [rad/s^2] as in dynamics();
    h_dot the climb rate (climb_rate). Returns h [N_OBS] and H [N_OBS x n].
    """
    k = model.k
    n = x.shape[0]
    V = x[0]
    alpha = x[1]
    m = k[MASS]
    A = k[AREA] / m
    rho = density(u, k)
    Fe, dFe = thrust(V, u[1], rho, k)
    C, dC = coefficients(x, u, model, rho, Fe, dFe)
    qbar = 0.5 * rho * V * V
    sa = math.sin(alpha)
    ca = math.cos(alpha)
    mcoef = k[AREA] * k[CHORD] / k[IYY]
    CX = C[1] * sa - C[0] * ca
    CZ = -C[1] * ca - C[0] * sa

    h = np.zeros(N_OBS)
    H = np.zeros((N_OBS, n))
    h[0] = V
    h[1] = alpha
    h[2] = x[2]
    h[3] = x[3]
    h[4] = qbar * mcoef * C[2] + Fe * k[ARM] / k[IYY] + inertial_coupling(u, k)
    h[5] = qbar * A * CX + Fe / m * math.cos(k[SIGMA_T])
    h[6] = qbar * A * CZ - Fe / m * math.sin(k[SIGMA_T])
    climb, dV, da, dt = climb_rate(x, u)
    h[7] = climb
    H[7, 0] = dV
    H[7, 1] = da
    H[7, 2] = dt

    H[0, 0] = 1.0
    H[1, 1] = 1.0
    H[2, 2] = 1.0
    H[3, 3] = 1.0
    for j in range(n):
        H[4, j] = qbar * mcoef * dC[2, j]
        H[5, j] = qbar * A * (dC[1, j] * sa - dC[0, j] * ca)
        H[6, j] = qbar * A * (-dC[1, j] * ca - dC[0, j] * sa)
    H[4, 0] += rho * V * mcoef * C[2] + dFe * k[ARM] / k[IYY]
    H[5, 0] += rho * V * A * CX + dFe / m * math.cos(k[SIGMA_T])
    H[6, 0] += rho * V * A * CZ - dFe / m * math.sin(k[SIGMA_T])
    # d(C_X)/d(alpha) and d(C_Z)/d(alpha) through sin and cos of alpha itself.
    H[5, 1] += qbar * A * (C[1] * ca + C[0] * sa)
    H[6, 1] += qbar * A * (C[1] * sa - C[0] * ca)
    sensor_placement(x, k, h, H)
    turn_placement(u, k, h)
    for i in range(model.bias_channel.shape[0]):
        h[model.bias_channel[i]] += x[model.bias_start + i]
        H[model.bias_channel[i], model.bias_start + i] = 1.0
    return h, H


def sensor_placement(x: FloatArray, k: FloatArray, h: FloatArray, H: FloatArray) -> None:
    """Move the alpha vane and the accelerometers from the CG to where they sit (in place).

    A point r = (x, z) of the body (x forward, z down) moves with V_cg + omega x r, so a
    vane there reads alpha_v = atan2(V sin(alpha) - q x, V cos(alpha) + q z), and
    accelerometers there add qdot x r + omega x (omega x r):
    a_x + qdot z - q^2 x and a_z - qdot x - q^2 z, qdot being h[4] (turn_placement adds
    the roll and yaw rates' terms).
    """
    V, alpha, q = x[0], x[1], x[3]
    xv, zv = k[VANE_X], k[VANE_Z]
    if xv != 0.0 or zv != 0.0:
        num = V * math.sin(alpha) - q * xv
        den = V * math.cos(alpha) + q * zv
        r2 = num * num + den * den
        h[1] = math.atan2(num, den)
        dnum = (math.sin(alpha), V * math.cos(alpha), -xv)
        dden = (math.cos(alpha), -V * math.sin(alpha), zv)
        for col, j in ((0, 0), (1, 1), (2, 3)):
            H[1, j] = (den * dnum[col] - num * dden[col]) / r2
    xa, za = k[ACCEL_X], k[ACCEL_Z]
    if xa != 0.0 or za != 0.0:
        h[5] += h[4] * za - q * q * xa
        h[6] += -h[4] * xa - q * q * za
        for j in range(H.shape[1]):
            H[5, j] += H[4, j] * za
            H[6, j] -= H[4, j] * xa
        H[5, 3] -= 2.0 * q * xa
        H[6, 3] -= 2.0 * q * za


def turn_placement(u: FloatArray, k: FloatArray, h: FloatArray) -> None:
    """The accelerometers' centripetal terms of the roll and yaw rates (in place): omega x
    (omega x r) adds -r^2 x + p r z to a_x and p r x - p^2 z to a_z (the roll and yaw
    accelerations' terms are left out: not measured). No state in them: H unchanged."""
    xa, za = k[ACCEL_X], k[ACCEL_Z]
    if xa != 0.0 or za != 0.0:
        _, p, r = bank(u)
        h[5] += -r * r * xa + p * r * za
        h[6] += p * r * xa - p * p * za


def air_relative(x: FloatArray, gust: FloatArray) -> FloatArray:
    """The state the air sees under a gust [u_g, w_g] [m/s], u_g along the flight path and
    w_g across it (small against V): airspeed V + u_g and angle of attack alpha + w_g / V;
    the rest unchanged."""
    xa = x.copy()
    xa[0] = x[0] + gust[0]
    xa[1] = x[1] + gust[1] / x[0]
    return xa


def observe_in_gust(
    x: FloatArray, u: FloatArray, gust: FloatArray, model: ModelArrays
) -> FloatArray:
    """What the sensors read of an aircraft whose motion over the ground is x, in a gust
    [u_g, w_g] or [u_g, w_g, q_g] (the simulators): the observations at the air-relative
    state. As in the filters' model, the aerodynamics behind qdot, a_x and a_z see the
    pitch rate q - q_g, while the gyro and the vane's lever arm see the body's q (the
    accelerometers' q^2 lever-arm term takes q - q_g, a second-order difference)."""
    xa = air_relative(x, gust)
    h, _ = observe(xa, u, model)
    h[N_OBS - 1] += climb_rate(x, u)[0] - climb_rate(xa, u)[0]  # over the ground
    if gust.shape[0] > 2:
        xq = xa.copy()
        xq[3] = x[3] - gust[2]
        ha, _ = observe(xq, u, model)
        for c in range(4, N_OBS - 1):
            h[c] = ha[c]
    return h


def wind_slope(x: FloatArray, u: FloatArray, gust: FloatArray, model: ModelArrays) -> FloatArray:
    """State derivative of an aircraft moving through air that moves (the simulators):
    gust [u_g, w_g] or [u_g, w_g, q_g], q_g the pitch gust (the aerodynamics see the pitch
    rate q - q_g; pitch_gust_rows).

    x holds the motion over the ground: V, alpha of the velocity against the ground, theta,
    q. The aerodynamics (and a propeller) see the air-relative state air_relative(x, gust),
    V_a and alpha_a, so lift and drag act across and along the air-relative velocity,
    which is turned by delta = alpha_a - alpha from the ground velocity; gravity and the
    kinematics act on the motion over the ground:

        Vdot     = (-D cos(delta) + L sin(delta) + Fe cos(alpha + sigma_T))/m + g G1
        alphadot = q + (-L cos(delta) - D sin(delta) - Fe sin(alpha + sigma_T))/(m V)
                   + (g/V) G2
        thetadot = q cos(phi) - r sin(phi)
        qdot     = (qbar_a S cbar/Iy) Cm + Fe arm/Iy + inertial coupling

    (G1, G2 of the bank: _angles; wings level -sin(theta - alpha) and cos(theta - alpha))

    with L, D, Cm at the air-relative state. In still air this is dynamics() exactly.
    (Applying dynamics() to the air-relative state instead, a shortcut that is exact in a
    steady wind, projects the forces on the air path rather than the ground path: an
    error of delta times the manoeuvre's acceleration, which put the NOC UAV's theta
    0.2 deg RMS off in light turbulence.)
    """
    k = model.k
    xa = air_relative(x, gust)
    if gust.shape[0] > 2:  # the pitch gust q_g: the aerodynamics see q - q_g
        xa[3] = x[3] - gust[2]
    Va = xa[0]
    V = x[0]
    alpha = x[1]
    rho = density(u, k)
    Fe, dFe = thrust(Va, u[1], rho, k)
    C, _ = coefficients(xa, u, model, rho, Fe, dFe)
    qbar = 0.5 * rho * Va * Va
    m = k[MASS]
    L = qbar * k[AREA] * C[1]
    D = qbar * k[AREA] * C[0]
    delta = xa[1] - alpha
    cd = math.cos(delta)
    sd = math.sin(delta)
    g = k[GRAV]
    angles = _angles(x, u, k)
    phi, _, r = bank(u)
    f = np.zeros(x.shape[0])
    f[0] = (-D * cd + L * sd + Fe * math.cos(alpha + k[SIGMA_T])) / m + g * angles[0]
    f[1] = (
        x[3] + (-L * cd - D * sd - Fe * math.sin(alpha + k[SIGMA_T])) / (m * V) + g / V * angles[1]
    )
    f[2] = x[3] * math.cos(phi) - r * math.sin(phi)
    f[3] = (
        qbar * k[AREA] * k[CHORD] / k[IYY] * C[2] + Fe * k[ARM] / k[IYY] + inertial_coupling(u, k)
    )
    return f


def fly_step(
    x: FloatArray, u0: FloatArray, u1: FloatArray, gust: FloatArray, h: float, model: ModelArrays
) -> FloatArray:
    """One classical Runge-Kutta step of the motion over the ground through a gust
    [u_g, w_g] held over h [s] (wind_slope), the inputs linear from u0 to u1."""
    um = u0 + 0.5 * (u1 - u0)
    f1 = wind_slope(x, u0, gust, model)
    f2 = wind_slope(x + 0.5 * h * f1, um, gust, model)
    f3 = wind_slope(x + 0.5 * h * f2, um, gust, model)
    f4 = wind_slope(x + h * f3, u1, gust, model)
    out: FloatArray = x + h / 6.0 * (f1 + 2.0 * f2 + 2.0 * f3 + f4)
    return out


def rk4_step(
    x: FloatArray,
    u0: FloatArray,
    u1: FloatArray,
    h: float,
    model: ModelArrays,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """One classical Runge-Kutta step of the filters' model x' = f(x, u(t)) (dynamics_rows:
    still air, or the gust states where the layout has them) over h [s], the inputs
    linear from u0 to u1 (u0 = u1: held). Returns x(t + h) and the Jacobians' rows
    F1..F4 [n_dynamic x n] at the four stages (the filters propagate the transition
    matrix from them)."""
    um = u0 + 0.5 * (u1 - u0)
    f1, F1 = dynamics_rows(x, u0, model)
    f2, F2 = dynamics_rows(x + 0.5 * h * f1, um, model)
    f3, F3 = dynamics_rows(x + 0.5 * h * f2, um, model)
    f4, F4 = dynamics_rows(x + h * f3, u1, model)
    return x + h / 6.0 * (f1 + 2.0 * f2 + 2.0 * f3 + f4), F1, F2, F3, F4
