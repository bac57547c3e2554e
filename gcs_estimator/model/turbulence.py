"""Turbulence: Dryden intensity presets and the gust process-noise densities the filters use.

The simulator flies the Dryden shaping filters themselves (sim.truth); the filters model
gusts as white process noise on V, alpha and theta scaled by a gust intensity sigma_w^2
(docs/model.md, "Turbulence").
"""

from __future__ import annotations

SIGMA_W_PRESETS: dict[str, float] = {"none": 0.0, "light": 0.772, "moderate": 1.543}
"""MIL-F-8785C low altitude vertical intensity sigma_w = 0.1*W20 [m/s], W20 = 15 kt
(light) or 30 kt (moderate)."""

SIGMA_U_RATIO = 1.5
"""sigma_u / sigma_w of the presets."""


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
