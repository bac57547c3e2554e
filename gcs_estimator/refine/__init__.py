"""Maximum likelihood over a whole record: `gcs-estimator refine`.

The filters give an estimate and a covariance online. Once the flight is over, the
record can be fitted as a whole: the initial state, the coefficients and the sensor
biases that make the model, flown through the record's inputs from its first frame,
reproduce the observations best.

    run.py           refine_run: a finished run refined, the method chosen ("auto")
    fit.py           refine: the fit of one record from a start, and its uncertainty
    output_error.py  output error (calm air), and filter error at held noise levels
    filter_error.py  filter error with a steady-state gain (turbulence)
    problem.py       the record, the model's output over it and its sensitivities
    flights.py       the model flown over the record (compiled, the filters' propagation)
    covariance.py    Cramer-Rao and Morelli-Klein covariances of the parameters
    structure.py     the structure sigma: the fit re-made with each channel trusted less
    sigma.py         the sigma to trust and its parts
    result.py        Refined, RefineProgress, RefineError

- Output error (calm air): the model flies open loop; with the noise unknown each
  Gauss-Newton iteration first sets each channel's variance to its mean squared output
  error (the relaxation method; Jategaonkar 2015, ch. 4).
- Filter error (turbulence, or anything the model misses): a Kalman filter with a
  steady-state gain corrects the flight states inside the fit, its process noise and the
  innovations' covariance estimated with the parameters (Maine and Iliff 1981;
  Jategaonkar 2015, ch. 5; decision 0021). With the noise held (the sensors' and the
  air's levels known), the time-varying extended Kalman filter at those levels.

The sigma to trust (sigma.py) starts from the Cramer-Rao bound, corrected for the
residuals' colour (Morelli-Klein), with the structure sigma (decision 0022; never less
than the filters' own check of the record, 0031) and, for a run's fit, the difference
from the filter it started from (0030).

Output error assumes calm air: in turbulence the filters' and filter error's estimates
are the better ones, and the residual colour shows it (the corrected sigma grows). The
method "auto" (the default) chooses from what the filters found: filter error where their
turbulence level over the final pass stands clear of zero, output error otherwise
(choose_method; decision 0025).
"""

from gcs_estimator.refine.fit import refine
from gcs_estimator.refine.problem import available_cores
from gcs_estimator.refine.result import Refined, RefineError, RefineProgress, fit_label
from gcs_estimator.refine.run import choose_method, refine_run
from gcs_estimator.uncertainty.sigma import FitSigma

__all__ = [
    "FitSigma",
    "RefineError",
    "RefineProgress",
    "Refined",
    "available_cores",
    "choose_method",
    "fit_label",
    "refine",
    "refine_run",
]
