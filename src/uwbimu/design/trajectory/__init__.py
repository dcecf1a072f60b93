"""Observability-aware trajectory design.

* :mod:`.seed_ocp` -- seed 002, sections XI-XII: point mass, three beacons,
  ``1/det(O)^2`` added to a quadratic tracking/control cost, solved by the
  indirect method (Pontryagin, gradient descent on ``u``) and by a direct
  method (CasADi + IPOPT), with the PD baseline.
* :mod:`.pointmass` -- general observability-aware planning for the point mass
  (any number of beacons, obstacles, bounds; log-det / E- / A-optimal
  objectives on the accumulated range information).
* :mod:`.calibration` -- calibration manoeuvre design for the 19-state
  UWB-IMU model (lever arm and time offset, E-optimal).
* :mod:`.proof` -- Monte Carlo proof of the calibration design with the ESKF.
* :mod:`.platform` -- platform models (multirotor limits and check, handheld).
"""

from uwbimu.design.trajectory.seed_ocp import (  # noqa: F401
    SeedOcpConfig,
    SeedOcpResult,
    det_observability,
    det_observability_grad,
    pd_rollout,
    rollout,
    seed_cost,
    solve_direct,
    solve_indirect,
    solve_seed_ocp,
)
