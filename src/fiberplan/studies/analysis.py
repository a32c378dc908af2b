"""Reading and summarising results tables: success and deadlock rates with Wilson intervals,
per-planner aggregates (makespan ratio, gap to central, wall time)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan.errors import StudyError


def load_results(path: str | Path) -> Any:
    """Read a study results table (pandas DataFrame)."""
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise StudyError(f"results table {str(path)!r} does not exist")
    try:
        return pd.read_parquet(path)
    except Exception as e:  # pyarrow raises its own types for a file that is not Parquet
        raise StudyError(f"results table {str(path)!r} is not a Parquet table ({type(e).__name__}: {e}); give the .parquet a sweep wrote") from e


def wilson_interval(successes: float, trials: float, z: float = 1.96) -> tuple[float, float]:
    r"""Wilson score interval of a binomial proportion.

    .. math:: \frac{\hat p + \frac{z^2}{2n} \pm z \sqrt{\frac{\hat p (1 - \hat p)}{n} + \frac{z^2}{4 n^2}}}{1 + z^2 / n}
    """
    if trials <= 0:
        return (math.nan, math.nan)
    p = successes / trials
    denom = 1 + z**2 / trials
    centre = (p + z**2 / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z**2 / (4 * trials**2)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def rates(frame: Any, by: Sequence[str], z: float = 1.96) -> Any:
    """Success and deadlock rates over positioners, with Wilson intervals, grouped by ``by``.

    Counts pool every positioner with a target across the runs of a group (``reached``,
    ``deadlocked``, ``targets`` columns); error runs are counted in ``errors`` and left out.
    """
    import pandas as pd

    ok = frame[frame["status"] == "ok"]
    rows = []
    for key, group in ok.groupby(list(by), dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        targets = float(group["targets"].sum())
        reached = float(group["reached"].sum())
        dead = float(group["deadlocked"].sum())
        s_lo, s_hi = wilson_interval(reached, targets, z)
        d_lo, d_hi = wilson_interval(dead, targets, z)
        rows.append(
            {
                **dict(zip(by, key, strict=True)),
                "runs": len(group),
                "targets": int(targets),
                "success_rate": reached / targets if targets else math.nan,
                "success_lo": s_lo,
                "success_hi": s_hi,
                "deadlock_rate": dead / targets if targets else math.nan,
                "deadlock_lo": d_lo,
                "deadlock_hi": d_hi,
                "runs_all_reached": float((group["reached"] == group["targets"]).mean()),
                "collisions": int(group["collisions"].sum()),
            }
        )
    errors = frame[frame["status"] != "ok"].groupby(list(by), dropna=False).size()
    out = pd.DataFrame(rows)
    if len(out):
        out["errors"] = [int(errors.get(tuple(r[b] for b in by) if len(by) > 1 else r[by[0]], 0)) for _, r in out.iterrows()]
    return out


def _quantiles(values: Sequence[float]) -> dict[str, float]:
    arr = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if len(arr) == 0:
        nan = float("nan")
        return {"median": nan, "p90": nan, "mean": nan, "max": nan, "n": 0}
    return {
        "median": float(np.median(arr)),
        "p90": float(np.percentile(arr, 90)),
        "mean": float(arr.mean()),
        "max": float(arr.max()),
        "n": len(arr),
    }


def aggregate(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per-planner aggregates: success, collisions, makespan ratio, gap to central, energy gap, wall time."""
    out: dict[str, dict[str, Any]] = {}
    for name in dict.fromkeys(r["planner"] for r in rows):
        mine = [r for r in rows if r["planner"] == name]
        ok = [r for r in mine if not r["error"]]
        rates = [r["success_rate"] for r in ok]
        out[name] = {
            "runs": len(mine),
            "errors": len(mine) - len(ok),
            "success_rate_mean": float(np.mean(rates)) if rates else float("nan"),
            "clean_fraction": float(np.mean([bool(r["clean"]) for r in mine])) if mine else float("nan"),
            "collisions_total": int(sum(int(r["collisions"]) for r in ok if math.isfinite(r["collisions"]))),
            "makespan_over_bound": _quantiles([r["makespan_over_bound"] for r in mine if r["clean"]]),
            "gap_to_central": _quantiles([r["gap_to_central"] for r in mine]),
            "energy_gap_to_central": _quantiles([r["energy_gap_to_central"] for r in mine]),
            "energy_rad2_s": _quantiles([r["energy_rad2_s"] for r in mine if r["clean"]]),
            "plan_wall_s": _quantiles([r["plan_wall_s"] for r in mine]),
        }
    return out
