"""Studies: one runner (scenario -> plan -> verify -> row) under sweeps, comparisons and benchmarks.

==============  ==========================================================================
``runner``      :class:`RunSpec`, :func:`run_one`: the one row of the one results format
``scenarios``   every scenario kind, ``hard`` included (:func:`study_scenario`)
``reference``   :func:`central_reference`, the verified central optimum
``sweep``       study files (TOML grids), local pools or Dask, resumable and loss-free
``compare``     planners side by side on the same scenarios, gaps to ``central``
``analysis``    reading tables: rates with Wilson intervals, per-planner aggregates
==============  ==========================================================================
"""

from fiberplan.errors import StudyError
from fiberplan.studies.analysis import aggregate, load_results, rates, wilson_interval
from fiberplan.studies.compare import CompareResult, add_gaps, format_table, run_compare, write_parquet
from fiberplan.studies.reference import central_reference
from fiberplan.studies.runner import ROW_COLUMNS, RunSpec, run_one, write_rows
from fiberplan.studies.scenarios import HARD_KIND, STUDY_KINDS, hard_scenario, study_scenario
from fiberplan.studies.sweep import (
    StudySpec,
    finished_tasks,
    load_study,
    lost_tasks,
    recorded_tasks,
    run_study,
    study_from_dict,
)

__all__ = [
    "HARD_KIND",
    "ROW_COLUMNS",
    "STUDY_KINDS",
    "CompareResult",
    "RunSpec",
    "StudyError",
    "StudySpec",
    "add_gaps",
    "aggregate",
    "central_reference",
    "finished_tasks",
    "format_table",
    "hard_scenario",
    "load_results",
    "load_study",
    "lost_tasks",
    "rates",
    "recorded_tasks",
    "run_compare",
    "run_one",
    "run_study",
    "study_from_dict",
    "study_scenario",
    "wilson_interval",
    "write_parquet",
    "write_rows",
]
