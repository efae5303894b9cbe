"""Model criticism: compare the calibrated model with measurements, locate and explain misfit.

The steps of ``skinid check`` (docs/criticism.md), one module each:

1. **Data** (:mod:`.data`): the measured fields at their points, the stated (correlated)
   noise and the model's own error carried next to it; whitening.
2. **Calibrate** (:mod:`.calibration`): Levenberg–Marquardt in the unit box of the prior,
   failed FE runs as rejected steps, exact Jacobians when the forward model has them; the
   posterior is the Laplace approximation at the optimum.
3. **Know the mesh's own error** (:mod:`.discretisation`): a two-mesh estimate at the
   calibrated parameters, used to correct the model and carried as a model-form variance.
4. **Compare and locate** (:mod:`.metrics`): RMSE, chi^2/dof, a posterior-predictive
   p-value, Moran's I against the noise model, regions ranked by standardised residual.
5. **Explain** (:mod:`.diagnosis`): a stated noise that does not fit, each candidate effect's
   score test, confirmation fits, Delta BIC and the verdict.
6. **Run and report** (:mod:`.check`, :mod:`.report`): the whole check on the FE model and
   its report.md / report.json / figures.
"""

from inference.criticism.calibration import Calibration, CalibrationError, calibrate
from inference.criticism.data import Data, NoiseModel
from inference.criticism.diagnosis import (
    CandidateScore,
    Diagnosis,
    NoiseStatement,
    check_noise_statement,
    diagnose,
    extend,
    verdict,
)
from inference.criticism.metrics import MembraneRegions, RegionResidual, ResidualMetrics, rank_regions, residual_metrics

__all__ = [
    "CandidateScore",
    "Calibration",
    "CalibrationError",
    "Data",
    "Diagnosis",
    "MembraneRegions",
    "NoiseModel",
    "NoiseStatement",
    "RegionResidual",
    "ResidualMetrics",
    "calibrate",
    "check_noise_statement",
    "diagnose",
    "extend",
    "rank_regions",
    "residual_metrics",
    "verdict",
]
