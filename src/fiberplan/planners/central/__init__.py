"""The ``central`` planner: one CasADi/IPOPT nonlinear program over a whole small group.

A *reference*, not a planner for thousands (``formulations/central.md``): it measures how
far the decentralised planners (``mpc``, ``dnf``) are from a centralised optimum, as
reference 004, section 7.5 does for the DNF. CasADi is imported by this module only.

Decision variables: the joint angles ``q[k]`` of every positioner at ``T + 1`` knots, the
scaled final time ``tau = t_f / t_LB`` (``t_LB`` the lower bound of ``metrics``), and one
separating line ``(n, c)`` per constrained body pair (a capsule, or a polygon zone whole) and interval. Velocities are
``u[k] = (q[k+1] - q[k]) / h`` with ``h = t_f / T`` (eliminated, so the dynamics and speed
bounds are linear in ``(q, t_f)``):

.. math::

    \\min\\; \\tau + w_E \\frac{E}{E_{ref}} \\quad (\\text{mode "time"}), \\qquad
    \\min\\; \\frac{E}{E_{ref}},\\; t_f \\text{ fixed} \\quad (\\text{mode "energy"}),
    \\qquad E = \\sum_k \\frac{\\|q[k+1] - q[k]\\|^2}{h}

    \\text{s.t.}\\; |q_{ij}[k+1] - q_{ij}[k]| \\le \\omega_j h, \\; q[k] \\in [q_{lo}, q_{hi}],
    \\; q[0] = q_{start},\\; q[T] = q_{target},

    n_\\ell \\cdot x - c_\\ell \\ge r_A + m/2 + \\delta_x(h) \\;\\; (x \\text{ an end point of } A \\text{ at } k, k+1),
    \\quad c_\\ell - n_\\ell \\cdot y \\ge r_B + m/2 + \\delta_y(h), \\quad \\|n_\\ell\\|^2 \\le 1,

where ``delta`` bounds how far a capsule end point strays from its chord between two knots
(so the linear joint motion between knots is covered, not only the knots). Lines are added
lazily: only for (pair, body pair, interval) triples that come within ``activate_mm`` of
contact along the current guess; after every solve the triples the solution brings close
are added and the problem is solved again (``lazy_rounds``).

The planner returns the best converged candidate of several warm starts; it never checks
itself. :func:`fiberplan.studies.central_reference` runs the independent verifier on the candidates
(best first) and returns the first verified one, marking the result ``failed`` if none passes.

Modules: ``settings``, ``nlp`` (the problem, one IPOPT solve, the lazy lines of one
candidate), ``solve`` (warm starts, :func:`solve_central`, :func:`plan_central`).
"""

from fiberplan.planners.central.nlp import Candidate, CentralSolution
from fiberplan.planners.central.settings import CentralSettings
from fiberplan.planners.central.solve import plan_central, result_of, solve_central

__all__ = ["Candidate", "CentralSettings", "CentralSolution", "plan_central", "result_of", "solve_central"]
