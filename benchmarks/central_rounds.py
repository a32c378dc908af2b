"""The central reference on one hard group from the mpc's trajectory, round by round::

    python benchmarks/central_rounds.py moons 19 0 '{"max_wall_s": 300, "activate_mm": 1.0, "activation_window": 1, "lazy_rounds": 10}'

Prints, for every NLP the candidate solves (its first and each lazy round): the time, the number
of lines, whether the round may start warm, the IPOPT status, iterations and seconds, and the
set-up; then the reference's status, whether the verifier passed it, its makespan and the lower
bound. Settings (JSON) override the central defaults; the start is the mpc's trajectory alone.
"""

from __future__ import annotations

import json
import sys
import time

import fiberplan.planners.central.nlp as nlp
from fiberplan.metrics import summarize
from fiberplan.planners import plan
from fiberplan.studies import central_reference
from fiberplan.studies.scenarios import hard_scenario

_solve_nlp = nlp._solve_nlp


def _logged(problem: nlp._Problem, active: object, guesses: list, *rest: object) -> tuple[dict, float]:
    raw, build_s = _solve_nlp(problem, active, guesses, *rest)
    print(f"   {time.strftime('%H:%M:%S')} lines {len(active)} warm {bool(rest and rest[0] is not None)} status {raw['status']} "
          f"iters {raw['iterations']} solve {raw['solve_s']:.2f} s set-up {build_s:.2f} s", flush=True)
    return raw, build_s


def main() -> None:
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    name, n, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    overrides = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    nlp._solve_nlp = _logged
    scenario = hard_scenario(name, n, seed)
    warm = plan(scenario, "mpc")
    print(f"mpc: makespan {summarize(warm)['makespan_s']:.3f} s", flush=True)
    started = time.perf_counter()
    result = central_reference(scenario, {**overrides, "warm_start": ["mpc"]}, warm_results=[warm])
    s = result.stats
    print(f"{name} {n} seed {seed}: wall {time.perf_counter() - started:.1f} s, {s.get('status')}, verified {s.get('verified')}, "
          f"makespan {s.get('makespan_s')} s, lower bound {s.get('lower_bound_s')} s", flush=True)


if __name__ == "__main__":
    main()
