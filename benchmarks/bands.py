"""The 95 % bands a consistent filter's mean NEES and mean NIS fall in."""

from __future__ import annotations

from scipy.stats import chi2


def mean_chi2_band(dof: float, runs: int) -> tuple[float, float]:
    """The 95 % band of the mean of `runs` independent chi-square draws of `dof` degrees
    of freedom each: a NEES over `runs` seeds (dof: the coefficients), or a NIS over
    `runs` updates (dof: the channels)."""
    return (
        float(chi2.ppf(0.025, dof * runs) / runs),
        float(chi2.ppf(0.975, dof * runs) / runs),
    )
