"""fiberplan: collision-free motion planning for theta-phi fiber positioner robots.

The public API in five names::

    from fiberplan import make_scenario, plan, verify, summarize, save_result

and motor profiles of a plan with ``discretise`` (:mod:`fiberplan.profiles`).
"""

from fiberplan.errors import FiberplanError, InstrumentError, PlannerError, ScenarioError, TrajectoryFileError
from fiberplan.generate import SCENARIO_KINDS, make_scenario
from fiberplan.instrument import Instrument
from fiberplan.instrument_io import load_instrument, preset_names
from fiberplan.metrics import summarize
from fiberplan.planners import make_settings, plan, planner_names
from fiberplan.profiles import JointProfile, Profiles, discretise
from fiberplan.scenario import Scenario, load_scenario
from fiberplan.trajectory import PlanResult, Trajectory, load_result, save_result
from fiberplan.verify import VerificationReport, verify

__all__ = [
    "SCENARIO_KINDS",
    "FiberplanError",
    "Instrument",
    "InstrumentError",
    "JointProfile",
    "PlanResult",
    "PlannerError",
    "Profiles",
    "Scenario",
    "ScenarioError",
    "Trajectory",
    "TrajectoryFileError",
    "VerificationReport",
    "discretise",
    "load_instrument",
    "load_result",
    "load_scenario",
    "make_scenario",
    "make_settings",
    "plan",
    "planner_names",
    "preset_names",
    "save_result",
    "summarize",
    "verify",
]
