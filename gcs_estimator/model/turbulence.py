"""Turbulence: Dryden intensity presets and the gust process-noise densities the filters use.

The simulator flies the Dryden shaping filters themselves (sim.truth); the filters model
gusts either as gust states (first-order Dryden processes in the augmented state) or as
white process noise on V, alpha and theta, scaled by a gust intensity sigma_w^2
(docs/model.md, "Turbulence").
"""

from __future__ import annotations

SIGMA_W_PRESETS: dict[str, float] = {"none": 0.0, "light": 0.772, "moderate": 1.543}
"""MIL-F-8785C low altitude vertical intensity sigma_w = 0.1*W20 [m/s], W20 = 15 kt
(light) or 30 kt (moderate)."""

SIGMA_U_RATIO = 1.5
"""sigma_u / sigma_w of the presets."""

THETA_DENSITY = 1.7e-6
"""The filters' white process noise on theta per unit sigma_w^2 [rad^2/s per (m/s)^2]
(gust_densities)."""


def gust_densities(
    airspeed_mps: float,
    sigma_u_ratio: float,
    length_u_m: float,
    length_w_m: float,
    theta_density: float,
) -> tuple[float, float, float, float]:
    """Spectral densities of V, alpha, theta, q per unit sigma_w^2.

    The air-relative V and alpha are driven by the derivative of the gusts; its density is
    at most the white (high-frequency) level of the Dryden filters:

        q_V = 2 sigma_u^2 V0 / L_u,    q_alpha = 3 sigma_w^2 / (L_w V0)

    Theta has no gust term of its own, but without `theta_density` the filter pins theta
    to the average of thousands of samples while the colour of the gusts moves it.
    """
    v = airspeed_mps
    return (
        2.0 * sigma_u_ratio**2 * v / length_u_m,
        3.0 / (length_w_m * v),
        theta_density,
        0.0,
    )


def gust_state_densities(
    airspeed_mps: float, sigma_u_ratio: float, length_u_m: float, length_w_m: float
) -> tuple[float, float]:
    """Spectral densities driving the gust states u_g, w_g per unit sigma_w^2.

    A first-order process x' = -(V/L) x + noise of density 2 sigma^2 V / L has the
    stationary variance sigma^2: Dryden's u_g exactly. Dryden's w_g is second order, and
    above 1/T_w = V/L_w its spectrum holds 3/2 of that first-order process's power; the
    filter sees turbulence mostly there (the innovations of one sample), so the w_g state
    is driven at 3 sigma_w^2 V / L_w, the white level of gust_densities (its stationary
    variance is then 1.5 sigma_w^2; matched at 2 sigma_w^2 V / L_w the online level came
    out sqrt(1.5) too high)."""
    v = airspeed_mps
    return 2.0 * sigma_u_ratio**2 * v / length_u_m, 3.0 * v / length_w_m
